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

A board's clock can also lose time at once (a simulated one drops a timer overflow: 3.3 ms). A
line through the samples on both sides of such a step bends its rate to join them, by a
thousand ppm for as long as the older samples are kept, and mispredicts the clock by ms (Idle
reported before the last step ran). So a reading that no line through the samples explains,
its rate free (see ``STEP_S``), starts a new segment: the segments share one rate, each with
its own offset, and the newest one's offset is the fit's.

The fit is plain Python over at most 64 samples, not numpy: it runs once a poll, after the
process has slept, and there numpy's machinery is what costs (on a shared VM, a numpy fit
after 0.3 s asleep took 0.2-1.4 ms against 17 us warm; this loop 0.06-0.3 ms against 12 us).
"""

from __future__ import annotations

from collections import deque

RATE_PRIOR = 100e-6
"""How far (a fraction) the rate is expected to be from nominal before the samples say: the
fit minimises the weighted squares plus ``((rate - nominal) / (RATE_PRIOR * nominal))**2``."""


STEP_S = 0.3e-3
"""A reading this far (seconds) outside its round trip's window, both as the fit predicts it
and by the best line through the samples and it with the rate free (no prior), is a step of
the board's clock: a new segment starts. The fit's error is a few tens of µs; a board whose
rate the fit has not yet learnt (the prior holds it near nominal for a few seconds) strays
further, but on a line."""

Sample = tuple[float, float, float, int]  # host time (the window's middle), clock, rtt, segment


def fit_line(samples: list[Sample] | deque[Sample], floor_s: float, prior: float,
             nominal_hz: float) -> tuple[float, float, float]:
    """``(freq, ref_s, offset)``: the weighted least-squares line, one rate shared by the
    segments and each its own offset, the newest segment's taken, the rate pulled towards
    ``nominal_hz`` with weight ``prior`` (1/s^2 of host time, the samples' weights' unit)."""
    ref_s, ref_clock = samples[-1][0], samples[-1][1]
    # per segment: the weights' sum, and the weighted sums of x, y, x*x and x*y
    sums: dict[int, list[float]] = {}
    for host_s, clock, rtt, segment in samples:
        w = 1.0 / ((rtt - floor_s) * (rtt - floor_s))
        x, y = host_s - ref_s, clock - ref_clock
        acc = sums.setdefault(segment, [0.0, 0.0, 0.0, 0.0, 0.0])
        acc[0] += w
        acc[1] += w * x
        acc[2] += w * y
        acc[3] += w * x * x
        acc[4] += w * x * y
    var = cov = 0.0
    for w_sum, wx, wy, wxx, wxy in sums.values():
        var += wxx - wx * wx / w_sum
        cov += wxy - wx * wy / w_sum
    freq = (cov + prior * nominal_hz) / (var + prior) if var + prior > 0.0 else nominal_hz
    if abs(freq / nominal_hz - 1.0) > 0.01:  # a reading from another clock: keep nominal
        freq = nominal_hz
    w_sum, wx, wy, _, _ = sums[samples[-1][3]]
    return freq, ref_s, ref_clock + (wy - freq * wx) / w_sum


class ClockSync:
    """The fitted host-to-MCU clock map; see the module docstring."""

    def __init__(self, nominal_hz: float, max_samples: int = 64) -> None:
        self.nominal_hz = nominal_hz
        self.freq_hz = nominal_hz
        self._ref_s = 0.0
        self._offset = 0.0
        self._samples: deque[Sample] = deque(maxlen=max_samples)
        self._segment = 0
        self.steps = 0  # how many steps of the board's clock the fit has seen (see STEP_S)
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
        sample = (0.5 * (sent_s + received_s), float(clock64), rtt_s, self._segment)
        if self._samples and self._is_step(sent_s, received_s, sample):
            self._segment += 1
            self.steps += 1
            sample = (*sample[:3], self._segment)
        self._samples.append(sample)
        self._fit()

    def _is_step(self, sent_s: float, received_s: float, sample: Sample) -> bool:
        """Whether ``sample`` is off the fit by a step (see STEP_S), not a rate unlearnt."""
        if abs(self._outside_s(sent_s, received_s, sample[1])) <= STEP_S:
            return False
        freq, ref_s, offset = fit_line([*self._samples, sample], self.min_rtt_s - 20e-6, 0.0,
                                       self.nominal_hz)
        low, high = (offset + freq * (host_s - ref_s) for host_s in (sent_s, received_s))
        return max(sample[1] - high, low - sample[1]) / freq > STEP_S

    def predict_error_s(self, sent_s: float, received_s: float, clock32: int) -> float:
        """How far (seconds) a reading falls outside the prediction for its window: 0 inside,
        positive ahead of it (no host stall does that), negative behind it (the board lost
        time, or went back). A host stall only widens the window: the reading stays inside."""
        return self._outside_s(sent_s, received_s, self.extend(clock32))

    def _outside_s(self, sent_s: float, received_s: float, clock: float) -> float:
        low, high = self.clock_at(sent_s), self.clock_at(received_s)
        return (max(clock - high, 0.0) - max(low - clock, 0.0)) / self.freq_hz

    def _fit(self) -> None:
        samples = self._samples
        ref_s = samples[-1][0]
        if ref_s - samples[0][0] < 0.05:  # the start's burst: the best round trip, nominal
            self.freq_hz = self.nominal_hz
            host_s, clock, _, _ = min(samples, key=lambda sample: sample[2])
            self._ref_s, self._offset = ref_s, clock + self.freq_hz * (ref_s - host_s)
            return
        # the weights are 1/s^2 of host time: the prior in the same units (see RATE_PRIOR)
        self.freq_hz, self._ref_s, self._offset = fit_line(
            samples, self.min_rtt_s - 20e-6, 1.0 / (RATE_PRIOR * RATE_PRIOR), self.nominal_hz)

    def clock_at(self, host_s: float) -> float:
        """MCU ticks (64-bit, fractional) at host time ``host_s``."""
        return self._offset + self.freq_hz * (host_s - self._ref_s)

    def host_at(self, clock: float) -> float:
        """Host seconds at MCU tick ``clock``."""
        return self._ref_s + (clock - self._offset) / self.freq_hz
