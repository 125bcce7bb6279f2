"""Print time to MCU clock: motion is timed in the MCU's own time base (pure).

The step generator's trajectory runs in print time (kernel seconds plus the lead). Steps and
outputs are scheduled at ``clock = ref_clock + hz·(t - ref_s)`` with ``hz`` the nominal
``CLOCK_FREQ`` of the MCU's dictionary, as Klipper's host does (print time = clock ÷
``CLOCK_FREQ``): a move's speed in MCU ticks is the commanded one whatever the host's estimate
of the MCU's clock says, and step intervals never follow the jitter of that estimate.

The clock fit (:mod:`.clocksync`) only anchors the schedule when it starts (nothing is
scheduled, so a jump harms nothing) and sets the host's deadlines. While motion goes on without
a pause the kernel's clock and the MCU's drift apart at their crystals' difference (tens of ppm
on real boards); once the schedule is ``drift_max_s`` away from the fit, its rate follows the
fit plus what closes the gap in ``SLEW_S`` (at most ``MAX_SLEW`` beyond the fitted rate) until
it is within a quarter of that again, then returns to nominal. So the lead a host stall can use
shrinks by at most ``drift_max_s``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
SLEW_S = 2.0
MAX_SLEW = 200e-6


class PrintClock:
    """The print-time-to-MCU-clock map; see the module docstring."""

    def __init__(self, nominal_hz: float, drift_max_s: float) -> None:
        self.nominal_hz = nominal_hz
        self.drift_max_s = drift_max_s
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
        """How far (seconds) the fit puts print time ``at_s`` from the schedule."""
        return (fitted_clock - float(self.clock(at_s))) / self.nominal_hz

    def steer(self, at_s: float, fitted_clock: float, fitted_hz: float) -> None:
        """From print time ``at_s`` on (nothing before it changes): nominal while the fit's
        clock for ``at_s`` is within ``drift_max_s``, else towards the fit (see above)."""
        drift = self.drift_s(at_s, fitted_clock)
        if abs(drift) > self.drift_max_s:
            self.correcting = True
        elif abs(drift) < 0.25 * self.drift_max_s:
            self.correcting = False
        hz = self.nominal_hz
        if self.correcting:
            limit = self.nominal_hz * MAX_SLEW
            hz = fitted_hz + min(limit, max(-limit, drift * self.nominal_hz / SLEW_S))
        if hz != self.hz:
            self.ref_clock, self.ref_s, self.hz = float(self.clock(at_s)), at_s, hz
