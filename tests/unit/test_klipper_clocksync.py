"""The clock fit (plain Python) is the weighted least-squares line numpy finds, weighted by
how close each round trip is to the best, its rate held towards nominal by a prior
(``RATE_PRIOR``: one more row of the least squares); a step of the board's clock starts a new
segment, which shares the rate and sets the offset."""

from __future__ import annotations

import random
from collections.abc import Callable

import numpy as np
import pytest

from server.backends.klipper.clocksync import RATE_PRIOR, ClockSync

HZ = 16_000_000.0


def polled(sync: ClockSync, count: int, rate: float, seed: int,
           lost_s: Callable[[float], float] = lambda _: 0.0) -> list[tuple[float, ...]]:
    """``count`` polls 0.4 s apart of a clock running at ``rate`` x nominal, each read at a
    random point of a round trip of 0.1-2 ms, ``lost_s(host_s)`` behind; the samples the fit
    holds."""
    rng = random.Random(seed)
    sync.reset(1000.0, 5_000_000)
    host_s = 1000.0
    for _ in range(count):
        host_s += 0.4
        rtt_s = rng.uniform(0.1e-3, 2e-3)
        read_s = host_s + rng.uniform(0.0, rtt_s)
        sync.add_sample(host_s, host_s + rtt_s, true_clock(read_s - lost_s(read_s), rate))
    return list(sync._samples)  # noqa: SLF001


def true_clock(host_s: float, rate: float) -> int:
    return 5_000_000 + round((host_s - 1000.0) * HZ * rate)


@pytest.mark.parametrize(("rate", "seed"), [(1.0, 1), (1.0001, 2), (0.9999, 3)])
def test_the_fit_is_numpy_s_weighted_least_squares_line(rate: float, seed: int) -> None:
    sync = ClockSync(HZ)
    samples = polled(sync, 80, rate, seed)  # more than it keeps: the last 64
    assert sync.steps == 0
    host = np.array([s[0] for s in samples])
    clock = np.array([s[1] for s in samples])
    rtt = np.array([s[2] for s in samples])
    weight = np.sqrt(1.0 / (rtt - sync.min_rtt_s + 20e-6) ** 2)
    # rows: w * (intercept + slope * x) = w * clock (w: 1/s of host time, a tick residual
    # scaled by 1/HZ), and the prior's: slope / (RATE_PRIOR * HZ) = 1 / RATE_PRIOR
    rows = np.vstack([np.column_stack([weight, weight * (host - host[-1])]) / HZ,
                      [[0.0, 1.0 / (RATE_PRIOR * HZ)]]])
    wanted = np.concatenate([weight * clock / HZ, [1.0 / RATE_PRIOR]])
    (intercept, slope), *_ = np.linalg.lstsq(rows, wanted, rcond=None)
    assert len(samples) == 64
    assert sync.freq_hz == pytest.approx(slope, rel=1e-9)
    assert sync.clock_at(host[-1]) == pytest.approx(intercept, abs=1.0)  # within a tick
    assert sync.freq_hz / HZ == pytest.approx(rate, abs=20e-6)


@pytest.mark.parametrize(("rate", "seed"), [(1.0005, 4), (0.9995, 5), (1.002, 6)])
def test_a_board_far_off_nominal_is_learnt_whatever_steps_it_seemed_to_take(
        rate: float, seed: int) -> None:
    """Up to 2,000 ppm off: the first seconds may stray past ``STEP_S`` before the samples
    outweigh the prior; any segment that starts still adds its own slope to the rate."""
    sync = ClockSync(HZ)
    polled(sync, 80, rate, seed)
    assert sync.freq_hz / HZ == pytest.approx(rate, abs=20e-6)
    host_s = 1000.0 + 80 * 0.4 + 0.4  # the next poll's time
    assert abs(sync.clock_at(host_s) - true_clock(host_s, rate)) / HZ < 0.1e-3


def test_a_clock_that_loses_time_at_once_keeps_its_rate_and_takes_the_new_offset() -> None:
    """A simulated board drops a timer overflow (65,536 ticks): the samples after it start a
    segment of their own. A line through both sides would bend its rate by over a thousand ppm
    for as long as the older samples stay, and mispredict the clock by ms."""
    lost_s = 65_536 / HZ
    sync = ClockSync(HZ)
    polled(sync, 40, 1.0, 7, lambda host_s: lost_s if host_s > 1008.0 else 0.0)
    host_s = 1000.0 + 40 * 0.4 + 0.4
    assert abs(sync.clock_at(host_s) - true_clock(host_s - lost_s, 1.0)) / HZ < 0.1e-3
    assert sync.freq_hz / HZ == pytest.approx(1.0, abs=20e-6)
    assert sync.steps == 1


def test_a_few_seconds_of_wide_round_trips_keep_the_rate_near_nominal() -> None:
    """The start's burst (0.1 ms round trips), then polls after sleeping (1-2 ms, the board
    reading its clock early in each): without the prior the rate is bent by hundreds of ppm
    (the polls' bias over their span) and the clock a second on is off by that."""
    sync = ClockSync(HZ)
    sync.reset(100.0, 0)
    for k in range(4):  # the burst
        sent_s = 100.0 + k * 0.0002
        sync.add_sample(sent_s, sent_s + 0.0001, round((sent_s + 0.00005 - 100.0) * HZ))
    for k in range(1, 5):  # polls 0.5 s apart, read 0.1 ms after sending, answered 1.5 ms on
        sent_s = 100.0 + 0.5 * k
        sync.add_sample(sent_s, sent_s + 0.0015, round((sent_s + 0.0001 - 100.0) * HZ))
    assert abs(sync.freq_hz / HZ - 1.0) < 30e-6
    assert abs(sync.clock_at(103.0) - 3.0 * HZ) / HZ < 150e-6  # 0.15 ms


def test_samples_too_close_together_keep_the_nominal_rate_from_the_best_round_trip() -> None:
    sync = ClockSync(HZ)
    sync.reset(10.0, 0)
    sync.add_sample(10.000, 10.002, 32_000)  # read 2 ms after, in a 2 ms round trip
    sync.add_sample(10.010, 10.0101, 161_600)  # the best: 0.1 ms
    assert sync.freq_hz == HZ
    assert sync.clock_at(10.01005) == pytest.approx(161_600, abs=1e-6)  # its midpoint
