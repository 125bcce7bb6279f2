"""Host seconds to MCU clock ticks, fitted from ``get_clock`` round trips (pure).

Each sample is a query sent at host time ``sent_s``, answered with the MCU's clock, and received
at ``received_s``: the MCU read its clock somewhere inside that window, most likely near the
middle, and the narrower the window the surer. The fit is a weighted least-squares line
``clock = offset + freq * (host_s - ref_s)`` over the recent samples, each weighted by how close
its round trip is to the best one seen, so a delayed answer barely moves it. The MCU's clock is
32 bits on the wire; :meth:`ClockSync.extend` unwraps it to 64 bits near the estimate.
"""

from __future__ import annotations

from collections import deque

import numpy as np


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
        host = np.array([s[0] for s in self._samples])
        clock = np.array([s[1] for s in self._samples])
        rtt = np.array([s[2] for s in self._samples])
        weight = 1.0 / (rtt - self.min_rtt_s + 20e-6) ** 2
        ref_s = float(host[-1])
        if len(host) < 2 or host[-1] - host[0] < 0.05:
            self._ref_s, self._offset = ref_s, float(clock[-1])
            self.freq_hz = self.nominal_hz
            best = int(np.argmax(weight))
            self._offset = float(clock[best] + self.freq_hz * (ref_s - host[best]))
            return
        x = host - ref_s
        w_sum = weight.sum()
        x_mean, y_mean = (weight * x).sum() / w_sum, (weight * clock).sum() / w_sum
        var = (weight * (x - x_mean) ** 2).sum()
        freq = (weight * (x - x_mean) * (clock - y_mean)).sum() / var
        if abs(freq / self.nominal_hz - 1.0) > 0.01:  # a reading from another clock: keep nominal
            freq = self.nominal_hz
        self.freq_hz = float(freq)
        self._ref_s, self._offset = ref_s, float(y_mean - freq * x_mean)

    def clock_at(self, host_s: float) -> float:
        """MCU ticks (64-bit, fractional) at host time ``host_s``."""
        return self._offset + self.freq_hz * (host_s - self._ref_s)

    def host_at(self, clock: float) -> float:
        """Host seconds at MCU tick ``clock``."""
        return self._ref_s + (clock - self._offset) / self.freq_hz
