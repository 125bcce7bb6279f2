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

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def step_target(position_steps: float) -> int:
    """The whole step an axis stands on at ``position_steps`` (round half up)."""
    return math.floor(position_steps + 0.5)


SCALAR_STEPS = 8
"""Pieces of at most this many steps are solved step by step (numpy's overhead per call is
that of about 30 steps in plain Python)."""


def _scalar_times(x0: float, u: float, v0: float, a: float, duration_s: float, current: int,
                  direction: int, count: int) -> list[float]:
    """:func:`crossing_times` for a few steps, one at a time (the same arithmetic)."""
    times, latest = [], 0.0
    stop_s = -v0 / a if a < 0.0 else 0.0
    for k in range(count):
        distance = max((current + direction * (k + 0.5) - x0) / u, 0.0)
        radicand = v0 * v0 + 2.0 * a * distance
        root = math.sqrt(max(radicand, 0.0))
        time_s = 2.0 * distance / (v0 + root) if v0 + root > 0.0 else duration_s
        if a < 0.0 and radicand < 0.0:
            time_s = stop_s
        latest = max(latest, min(max(time_s, 0.0), duration_s))
        times.append(latest)
    return times


def crossing_times(
    x0: float, u: float, v0: float, a: float, duration_s: float, current: int, target: int
) -> FloatArray:
    """Seconds from the piece start at which each step from ``current`` to ``target`` happens.

    Args:
        x0: axis position in steps at the piece start.
        u: steps per mm of path (signed; the axis' share of the direction).
        v0, a: path speed (mm/s) and acceleration (mm/s²) at the start.
        duration_s: length of the piece; times are clamped to ``[0, duration_s]``.
        current, target: whole-step positions before and after the piece.
    Returns:
        ``abs(target - current)`` non-decreasing times.
    """
    count = abs(target - current)
    if count == 0:
        return np.empty(0)
    direction = 1 if target > current else -1
    if count <= SCALAR_STEPS and u != 0.0:  # a short piece (a raster's): numpy costs more
        return np.array(_scalar_times(x0, u, v0, a, duration_s, current, direction, count))
    boundaries = current + direction * (np.arange(count, dtype=np.float64) + 0.5)
    if u == 0.0:
        return np.full(count, duration_s)
    distance = np.maximum((boundaries - x0) / u, 0.0)
    root = np.sqrt(np.maximum(v0 * v0 + 2.0 * a * distance, 0.0))
    denominator = v0 + root
    with np.errstate(divide="ignore", invalid="ignore"):
        times = np.where(denominator > 0.0, 2.0 * distance / denominator, duration_s)
    if a < 0.0:  # a boundary beyond the stopping point (rounding): at the stop
        stop_s = -v0 / a
        times = np.where(v0 * v0 + 2.0 * a * distance < 0.0, stop_s, times)
    times = np.clip(times, 0.0, duration_s)
    return np.maximum.accumulate(times)
