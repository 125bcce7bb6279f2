"""The clock fit (plain Python) is the weighted least-squares line numpy finds, weighted by
how close each round trip is to the best."""

from __future__ import annotations

import random

import numpy as np
import pytest

from server.backends.klipper.clocksync import ClockSync

HZ = 16_000_000.0


def polled(sync: ClockSync, count: int, rate: float, seed: int) -> list[tuple[float, float, float]]:
    """``count`` polls 0.4 s apart of a clock running at ``rate`` x nominal, each read at a
    random point of a round trip of 0.1-2 ms; the samples the fit holds."""
    rng = random.Random(seed)
    sync.reset(1000.0, 5_000_000)
    host_s = 1000.0
    for _ in range(count):
        host_s += 0.4
        rtt_s = rng.uniform(0.1e-3, 2e-3)
        read_s = host_s + rng.uniform(0.0, rtt_s)
        sync.add_sample(host_s, host_s + rtt_s, 5_000_000 + round((read_s - 1000.0) * HZ * rate))
    return list(sync._samples)  # noqa: SLF001


@pytest.mark.parametrize(("rate", "seed"), [(1.0, 1), (1.0002, 2), (0.9995, 3)])
def test_the_fit_is_numpy_s_weighted_least_squares_line(rate: float, seed: int) -> None:
    sync = ClockSync(HZ)
    samples = polled(sync, 80, rate, seed)  # more than it keeps: the last 64
    host = np.array([s[0] for s in samples])
    clock = np.array([s[1] for s in samples])
    rtt = np.array([s[2] for s in samples])
    weight = 1.0 / (rtt - sync.min_rtt_s + 20e-6) ** 2
    slope, intercept = np.polyfit(host - host[-1], clock, 1, w=np.sqrt(weight))
    assert len(samples) == 64
    assert sync.freq_hz == pytest.approx(slope, rel=1e-9)
    assert sync.clock_at(host[-1]) == pytest.approx(intercept, abs=1.0)  # within a tick
    assert sync.freq_hz / HZ == pytest.approx(rate, abs=20e-6)


def test_samples_too_close_together_keep_the_nominal_rate_from_the_best_round_trip() -> None:
    sync = ClockSync(HZ)
    sync.reset(10.0, 0)
    sync.add_sample(10.000, 10.002, 32_000)  # read 2 ms after, in a 2 ms round trip
    sync.add_sample(10.010, 10.0101, 161_600)  # the best: 0.1 ms
    assert sync.freq_hz == HZ
    assert sync.clock_at(10.01005) == pytest.approx(161_600, abs=1e-6)  # its midpoint
