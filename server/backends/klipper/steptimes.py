"""Exact step times of one axis along a constant-acceleration piece of trajectory (pure).

Along a piece the distance travelled is ``d(t) = v0·t + a·t²/2`` and the axis position in steps
``x(t) = x0 + u·d(t)`` (``u`` = unit component × steps/mm). The axis is commanded to step
``round_half_up(x)``, so a step happens each time ``x`` crosses a half-integer: solving
``d(t) = (b - x0)/u`` for those boundaries ``b`` gives every step's exact time. The count of
steps from a position to the next is exact whatever the floating point, because the caller
carries the integer position and the end target from piece to piece.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from server.backends.klipper.stepcore import solve

FloatArray = npt.NDArray[np.float64]


def step_target(position_steps: float) -> int:
    """The whole step an axis stands on at ``position_steps`` (round half up)."""
    return math.floor(position_steps + 0.5)


@dataclass(slots=True)
class Spans:
    """One axis' stretches of pieces whose steps are solved together: one compiled pass for all
    that a flush generates, whatever the number of pieces (a raster's have a few steps each).
    A span: the axis position in steps at its piece's start ``x0``, steps per mm of path ``u``
    (not 0), start speed and acceleration, how far into the piece (s), the whole steps before
    and after, and the print time its piece starts."""

    rows: list[tuple[float, float, float, float, float, float, float, float]] = field(
        default_factory=list)  # x0, u, v0, a, duration, first boundary, direction, base
    counts: list[int] = field(default_factory=list)
    total: int = 0  # steps of all the spans

    def add(self, x0: float, u: float, v0: float, a: float, duration_s: float, current: int,
            target: int, base_s: float) -> None:
        direction = 1 if target > current else -1
        count = abs(target - current)
        self.rows.append((x0, u, v0, a, duration_s, current + 0.5 * direction, direction,
                          base_s))
        self.counts.append(count)
        self.total += count

    def solve(self, to_clock: tuple[float, float, float] = (0.0, 1.0, 0.0)) -> FloatArray:
        """Every step's print time, ascending (span after span),
        or with ``to_clock`` = ``(ref_clock, hz, ref_s)`` its MCU clock
        ``ref_clock + hz·(t - ref_s)`` (the print clock's affine map, in the same pass).

        Solving ``d(t) = (b - x0)/u`` as ``t = 2d / (v0 + sqrt(v0² + 2ad))`` (no cancellation
        near standstill), clamped to the span; beyond a decelerating piece's stop (rounding)
        the square root is 0 and the clamp puts the step at the piece's end. Compiled
        (``_stepcore.c``): one pass, no numpy temporaries."""
        out = np.empty(self.total)
        solve(self.rows, self.counts, out, *to_clock)
        return out


def crossing_times(
    x0: float, u: float, v0: float, a: float, duration_s: float, current: int, target: int
) -> FloatArray:
    """Seconds from the piece start at which each step from ``current`` to ``target`` happens
    (one piece of :class:`Spans`).

    Args:
        x0: axis position in steps at the piece start.
        u: steps per mm of path (signed, not 0; the axis' share of the direction).
        v0, a: path speed (mm/s) and acceleration (mm/s²) at the start.
        duration_s: length of the piece; times are clamped to ``[0, duration_s]``.
        current, target: whole-step positions before and after the piece.
    Returns:
        ``abs(target - current)`` non-decreasing times.
    """
    if target == current:
        return np.empty(0)
    spans = Spans()
    spans.add(x0, u, v0, a, duration_s, current, target, 0.0)
    return spans.solve()
