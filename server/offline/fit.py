"""Whether a job fits the machine's travel where it is placed: pure, from the job's extent.

The extent comes from the offline pipeline (:func:`server.offline.estimate.estimate`) run from
the machine's real state (position, work offsets, modal state) with soft limits off, so it is
in machine coordinates under the current placement. :func:`check_fit` compares it with the
travel per axis and, for an axis that does not fit, says by how much and where the work origin
would have to be for it to fit (when the job is not larger than the travel). Units: mm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

FIT_SLACK_MM = 1e-6  # rounding of the pipeline; the interpreter's own slack is smaller


@dataclass(frozen=True, slots=True)
class AxisMisfit:
    """One axis of a job that leaves the travel.

    Attributes:
        axis: the axis name (``X``).
        below_mm: how far the job goes under the travel's minimum (0 if it does not).
        above_mm: how far the job goes over the travel's maximum (0 if it does not).
        origin_low_mm, origin_high_mm: the work origins (machine mm, this axis's work
            offset) from which the job would fit, or None when the job is larger than the
            travel.
    """

    axis: str
    below_mm: float
    above_mm: float
    origin_low_mm: float | None
    origin_high_mm: float | None

    def describe(self) -> str:
        side = (f"{self.below_mm:.3f} mm below the travel's minimum" if self.below_mm
                else f"{self.above_mm:.3f} mm beyond the travel's maximum")
        if self.origin_low_mm is None or self.origin_high_mm is None:
            return f"{self.axis}: {side}; the job is larger than the travel"
        if abs(self.origin_high_mm - self.origin_low_mm) < 0.0005:
            where = f"at {self.origin_low_mm:.3f}"
        else:
            where = f"between {self.origin_low_mm:.3f} and {self.origin_high_mm:.3f}"
        return f"{self.axis}: {side}; it fits with the {self.axis} work origin {where} (machine)"


@dataclass(frozen=True, slots=True)
class Fit:
    """A job's extent (machine mm) against the travel; ``misfits`` empty when it fits."""

    extent_min_mm: tuple[float, ...]
    extent_max_mm: tuple[float, ...]
    misfits: tuple[AxisMisfit, ...] = field(default=())

    @property
    def fits(self) -> bool:
        return not self.misfits

    def describe(self) -> str:
        """One line: ``fits`` or every axis that does not, for a person."""
        if self.fits:
            return "the job fits the travel"
        return "the job does not fit the travel: " + "; ".join(m.describe() for m in self.misfits)

    def as_dict(self, axis_names: Sequence[str]) -> dict[str, object]:
        """JSON-able: extent per axis, size per axis, and each misfit."""
        names = axis_names if self.extent_min_mm else ()  # a job without moves: no extent
        low, high = self.extent_min_mm, self.extent_max_mm
        return {
            "fits": self.fits,
            "extent_min_mm": dict(zip(names, low, strict=True)),
            "extent_max_mm": dict(zip(names, high, strict=True)),
            "size_mm": {n: b - a for n, a, b in zip(names, low, high, strict=True)},
            "misfits": [
                {"axis": m.axis, "below_mm": m.below_mm, "above_mm": m.above_mm,
                 "origin_low_mm": m.origin_low_mm, "origin_high_mm": m.origin_high_mm}
                for m in self.misfits
            ],
            "message": self.describe(),
        }


def check_fit(
    extent_min_mm: Sequence[float],
    extent_max_mm: Sequence[float],
    travel_min_mm: Sequence[float],
    travel_max_mm: Sequence[float],
    axis_names: Sequence[str],
    wco_mm: Sequence[float],
) -> Fit:
    """The job's extent (machine mm, placed with work offset ``wco_mm``) against the travel.

    An empty extent (a job without moves) fits."""
    if not extent_min_mm:
        return Fit((), ())
    misfits = []
    for i, name in enumerate(axis_names):
        low, high = extent_min_mm[i], extent_max_mm[i]
        below = max(0.0, travel_min_mm[i] - low)
        above = max(0.0, high - travel_max_mm[i])
        if below <= FIT_SLACK_MM and above <= FIT_SLACK_MM:
            continue
        origin_low = wco_mm[i] + (travel_min_mm[i] - low)
        origin_high = wco_mm[i] + (travel_max_mm[i] - high)
        fits_somewhere = origin_low <= origin_high + FIT_SLACK_MM
        misfits.append(AxisMisfit(
            name, round(below, 6) if below > FIT_SLACK_MM else 0.0,
            round(above, 6) if above > FIT_SLACK_MM else 0.0,
            round(origin_low, 6) if fits_somewhere else None,
            round(origin_high, 6) if fits_somewhere else None,
        ))
    return Fit(tuple(extent_min_mm), tuple(extent_max_mm), tuple(misfits))


def frame_lines(fit: Fit, feed_mm_min: float, power_s: float) -> list[str]:
    """The G-code that traces a job's XY bounding rectangle in machine coordinates (G53).

    With ``power_s`` 0 the laser stays off: four jogs (``$J=``, which change no modal state
    and which a hold cancels); else a rapid to the first corner, ``M3 S<power_s>``, four
    ``G1`` moves and ``M5`` (a diode laser's visible low-power frame; this leaves G1, F and S
    modal, as any cut would). Empty for a job without moves."""
    if not fit.extent_min_mm:
        return []
    (x0, y0), (x1, y1) = fit.extent_min_mm[:2], fit.extent_max_mm[:2]
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
    feed = f"F{feed_mm_min:g}"
    if power_s <= 0:
        return [f"$J=G53 G21 X{x:.3f} Y{y:.3f} {feed}" for x, y in corners]
    first, *rest = corners
    return [f"G53 G0 X{first[0]:.3f} Y{first[1]:.3f}", f"M3 S{power_s:g}",
            *(f"G53 G1 X{x:.3f} Y{y:.3f} {feed}" for x, y in rest), "M5"]
