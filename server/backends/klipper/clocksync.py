"""Host seconds to MCU clock ticks, fitted from ``get_clock`` round trips (pure).

Each sample is a query sent at host time ``sent_s``, answered with the MCU's clock, and received
at ``received_s``: the MCU read its clock somewhere inside that window, most likely near the
middle, and the narrower the window the surer. The fit is a weighted least-squares line
``clock = offset + freq * (host_s - ref_s)`` over the recent samples, each weighted by how close
its round trip is to the best one seen, so a delayed answer barely moves it. The MCU's clock is
32 bits on the wire; :meth:`ClockSync.extend` unwraps it to 64 bits near the estimate.

The rate has a prior: the nominal ``CLOCK_FREQ``, within ``RATE_PRIOR`` (a crystal's
tolerance), so a fit of a few seconds' samples, whose rate a round trip's width over that span
would bend by hundreds of ppm (a poll after the process slept takes 1-3 ms; the start's burst
0.1 ms), keeps near nominal until the samples span enough time to say otherwise (a board off by
200 ppm is followed within seconds; one whose clock lost time is reset, see :mod:`.mcu`).

The fit is plain Python over at most 64 samples, not numpy: it runs once a poll, after the
process has slept, and there numpy's machinery is what costs (on a shared VM, a numpy fit
after 0.3 s asleep took 0.2-1.4 ms against 17 us warm; this loop 0.06-0.3 ms against 12 us).
"""

from __future__ import annotations

from collections import deque

RATE_PRIOR = 100e-6
"""How far (a fraction) the rate is expected to be from nominal before the samples say: the
fit minimises the weighted squares plus ``((rate - nominal) / (RATE_PRIOR * nominal))**2``."""


class ClockSync:
    """The fitted host-to-MCU clock map; see the module docstring."""

    def __init__(self, nominal_hz: float, max_samples: int = 64) -> None:
        self.nominal_hz = nominal_hz
        self.freq_hz = nominal_hz
        self._ref_s = 0.0
        self._offset = 0.0
        self._samples: deque[tuple[float, float, float]] = deque(maxlen=max_samples)
        self._last_clock = 0
        self.min_rtt_s = float("inf")

    @property
    def synced(self) -> bool:
        return bool(self._samples)

    def reset(self, host_s: float, clock64: int) -> None:
        """Start over from one reading (after ``get_uptime`` or an MCU restart)."""
        self._samples.clear()
        self.min_rtt_s = float("inf")
        self.freq_hz = self.nominal_hz
        self._ref_s, self._offset = host_s, float(clock64)
        self._last_clock = clock64

    @property
    def last_clock(self) -> int:
        """The latest MCU clock read so far (64-bit)."""
        return self._last_clock

    def extend(self, clock32: int) -> int:
        """The 64-bit clock whose low 32 bits are ``clock32``, nearest the last one seen."""
        delta = (clock32 - self._last_clock) & 0xFFFFFFFF
        if delta & 0x80000000:
            delta -= 1 << 32
        return self._last_clock + delta

    def add_sample(self, sent_s: float, received_s: float, clock64: int) -> None:
        """One ``get_clock`` round trip; refits the map."""
        rtt_s = max(received_s - sent_s, 1e-7)
        self.min_rtt_s = min(self.min_rtt_s, rtt_s)
        self._last_clock = max(self._last_clock, clock64)
        self._samples.append((0.5 * (sent_s + received_s), float(clock64), rtt_s))
        self._fit()

    def predict_error_s(self, sent_s: float, received_s: float, clock32: int) -> float:
        """How far (seconds) a reading falls outside the prediction for its window: 0 inside,
        positive ahead of it (no host stall does that), negative behind it (the board lost
        time, or went back). A host stall only widens the window: the reading stays inside."""
        clock = self.extend(clock32)
        low, high = self.clock_at(sent_s), self.clock_at(received_s)
        return (max(clock - high, 0.0) - max(low - clock, 0.0)) / self.freq_hz

    def _fit(self) -> None:
        samples = self._samples
        floor_s = self.min_rtt_s - 20e-6
        weights = [1.0 / ((rtt - floor_s) * (rtt - floor_s)) for _, _, rtt in samples]
        ref_s = samples[-1][0]
        if len(samples) < 2 or ref_s - samples[0][0] < 0.05:
            self.freq_hz = self.nominal_hz
            best = max(range(len(samples)), key=weights.__getitem__)
            host_s, clock, _ = samples[best]
            self._ref_s, self._offset = ref_s, clock + self.freq_hz * (ref_s - host_s)
            return
        points = [(w, host_s - ref_s, clock)
                  for w, (host_s, clock, _) in zip(weights, samples, strict=True)]
        w_sum = sum(weights)
        x_mean = sum(w * x for w, x, _ in points) / w_sum
        y_mean = sum(w * y for w, _, y in points) / w_sum
        var = cov = 0.0
        for w, x, y in points:
            dx = x - x_mean
            var += w * dx * dx
            cov += w * dx * (y - y_mean)
        # the weights are 1/s^2 of host time: the prior in the same units (see RATE_PRIOR)
        prior = 1.0 / (RATE_PRIOR * RATE_PRIOR)
        freq = (cov + prior * self.nominal_hz) / (var + prior)
        if abs(freq / self.nominal_hz - 1.0) > 0.01:  # a reading from another clock: keep nominal
            freq = self.nominal_hz
        self.freq_hz = freq
        self._ref_s, self._offset = ref_s, y_mean - freq * x_mean

    def clock_at(self, host_s: float) -> float:
        """MCU ticks (64-bit, fractional) at host time ``host_s``."""
        return self._offset + self.freq_hz * (host_s - self._ref_s)

    def host_at(self, clock: float) -> float:
        """Host seconds at MCU tick ``clock``."""
        return self._ref_s + (clock - self._offset) / self.freq_hz
