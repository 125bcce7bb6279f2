"""Print time to MCU clock: motion is timed in the MCU's own time base (pure).

The step generator's trajectory runs in print time (kernel seconds plus the lead). Steps and
outputs are scheduled at ``clock = ref_clock + hz·(t - ref_s)`` with ``hz`` the nominal
``CLOCK_FREQ`` of the MCU's dictionary, as Klipper's host does (print time = clock ÷
``CLOCK_FREQ``): a move's speed in MCU ticks is the commanded one whatever the host's estimate
of the MCU's clock says, and step intervals never follow the jitter of that estimate.

The clock fit (:mod:`.clocksync`) only anchors the schedule when it starts (nothing is
scheduled, so a jump harms nothing) and sets the host's deadlines. While motion goes on without
a pause the schedule and the board's clock as fitted come apart: the crystals' difference (tens
of ppm on real boards), or a board that fell behind and caught up (a simulated one on a loaded
host, which also bends the fit's rate by thousands of ppm for a while). The drift is how far
ahead of the schedule the fit puts the board's clock where steps are being scheduled:

* behind (negative: each step comes later than planned; the lead grows, the host stall the MCU
  rides through with it) is harmless up to ``behind_max_s``;
* ahead (positive: the lead shrinks, and the stall the MCU rides through by as much) is
  allowed up to ``ahead_max_s``.

Beyond either bound the schedule's rate becomes the nominal one plus or minus a slew towards
the fit, proportional to the drift (``|drift| / SLEW_S``, at most ``MAX_SLEW``), until the
drift is within a quarter of that bound again; then nominal again. The rate never takes the
fit's own: a fit bent by thousands of ppm moves no step interval by more than ``MAX_SLEW``,
and only once the drift is past its bound. A board whose clock runs ``x`` ppm off the host's
(``x`` ≤ ``MAX_SLEW``) settles ``x``·``SLEW_S`` away (10 ms at 200 ppm); one ahead faster than
``MAX_SLEW`` would starve (its steps then go out late: the backend halts, never sends one late).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
SLEW_S = 50.0
"""The slew is the drift spread over this long (10 ms: 200 ppm)."""
MAX_SLEW = 500e-6


class PrintClock:
    """The print-time-to-MCU-clock map; see the module docstring."""

    def __init__(self, nominal_hz: float, ahead_max_s: float, behind_max_s: float) -> None:
        self.nominal_hz = nominal_hz
        self.ahead_max_s, self.behind_max_s = ahead_max_s, behind_max_s
        self.ref_s, self.ref_clock, self.hz = 0.0, 0.0, 0.0  # hz 0: not anchored
        self.correcting = False

    @property
    def anchored(self) -> bool:
        return self.hz != 0.0

    def unanchor(self) -> None:
        self.hz, self.correcting = 0.0, False

    def anchor(self, at_s: float, clock: float) -> None:
        """Print time ``at_s`` happens at MCU ``clock`` (a whole tick), at the nominal rate."""
        self.ref_s, self.ref_clock, self.hz = at_s, float(round(clock)), self.nominal_hz
        self.correcting = False

    def clock(self, t_s: float | FloatArray) -> float | FloatArray:
        """The MCU clock (fractional ticks) of print time ``t_s``."""
        return self.ref_clock + self.hz * (t_s - self.ref_s)

    def time_at(self, clock: float) -> float:
        """The print time of MCU ``clock``."""
        return self.ref_s + (clock - self.ref_clock) / self.hz

    def drift_s(self, at_s: float, fitted_clock: float) -> float:
        """How far (seconds) the fit puts the board's clock ahead of the schedule at print time
        ``at_s`` (negative: behind)."""
        return (fitted_clock - float(self.clock(at_s))) / self.nominal_hz

    def steer(self, at_s: float, fitted_clock: float) -> None:
        """From print time ``at_s`` on (nothing before it changes): nominal while the drift is
        within its bound, else nominal ± a bounded slew towards the fit (see above)."""
        drift = self.drift_s(at_s, fitted_clock)
        bound = self.ahead_max_s if drift > 0.0 else self.behind_max_s
        if abs(drift) > bound:
            self.correcting = True
        elif abs(drift) < 0.25 * bound:
            self.correcting = False
        hz = self.nominal_hz
        if self.correcting:
            slew = min(MAX_SLEW, abs(drift) / SLEW_S)
            hz = self.nominal_hz * (1.0 + math.copysign(slew, drift))
        if hz != self.hz:
            self.ref_clock, self.ref_s, self.hz = float(self.clock(at_s)), at_s, hz
