"""Clock sync, exact step times and step compression (pure cores of the Klipper backend)."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.stepcompress import StepCompressor, run_clocks
from server.backends.klipper.stepcore import StepAxis, off_track, piece_steps
from server.backends.klipper.steptimes import Spans, crossing_times, step_target
from tests.support.klipper_dictionary import dictionary_data

CLOCK_HZ = 72e6


def test_clock_fit_recovers_frequency_and_offset_within_a_few_microseconds() -> None:
    rng = random.Random(3)
    true_hz, offset = CLOCK_HZ * (1 + 60e-6), 123_456_789.0
    sync = ClockSync(CLOCK_HZ)
    sync.reset(0.0, int(offset))
    for i in range(40):
        sent = 0.25 * i + rng.uniform(0, 0.01)
        rtt = 150e-6 + (rng.expovariate(1 / 2e-3) if rng.random() < 0.3 else rng.uniform(0, 5e-5))
        read_at = sent + rng.uniform(0.45, 0.55) * rtt  # a symmetric link
        sync.add_sample(sent, sent + rtt, int(offset + true_hz * read_at))
    for host_s in (5.0, 10.0, 10.5):
        error_s = (sync.clock_at(host_s) - (offset + true_hz * host_s)) / true_hz
        assert abs(error_s) < 10e-6
    assert abs(sync.freq_hz / true_hz - 1) < 2e-6


def test_the_32_bit_clock_unwraps_near_the_estimate() -> None:
    sync = ClockSync(CLOCK_HZ)
    sync.reset(0.0, 2**32 - 100)
    assert sync.extend(50) == 2**32 + 50
    assert sync.extend(2**32 - 200) == 2**32 - 200


def brute_force_times(x0: float, u: float, v0: float, a: float, dur: float) -> list[float]:
    """Steps found by sampling the position densely (the reference)."""
    times = np.linspace(0.0, dur, 2_000_001)
    x = x0 + u * (v0 * times + 0.5 * a * times * times)
    steps = np.floor(x + 0.5)
    return [float(times[i]) for i in np.flatnonzero(np.diff(steps)) + 1]


def test_step_times_match_a_dense_sampling_of_the_trajectory() -> None:
    for x0, u, v0, a, dur in [(0.2, 80.0, 0.0, 3000.0, 0.05), (10.4, -57.0, 90.0, -1500.0, 0.06),
                              (-3.0, 400.0, 10.0, 0.0, 0.1)]:
        end = x0 + u * (v0 * dur + 0.5 * a * dur * dur)
        exact = crossing_times(x0, u, v0, a, dur, step_target(x0), step_target(end))
        reference = brute_force_times(x0, u, v0, a, dur)
        assert len(exact) == len(reference) == abs(step_target(end) - step_target(x0))
        assert np.max(np.abs(exact - np.array(reference))) < 2 * dur / 2_000_000


def test_the_steps_of_many_pieces_solved_at_once_are_each_pieces_own() -> None:
    """A flush solves all its pieces in one pass (Spans): the same times as piece by piece,
    through reversals, standstills and pieces a few steps long, and runs split by direction."""
    rng = random.Random(11)
    spans, expected, runs = Spans(), [], []
    position, base_s = 0, 100.0
    for _ in range(300):
        u = rng.choice([80.0, -80.0, 56.6, -13.0])
        v0, a = rng.choice([(0.0, 2000.0), (60.0, 0.0), (60.0, -1500.0), (5.0, 300.0)])
        duration_s = rng.uniform(0.0002, 0.04)
        if a < 0.0:
            duration_s = min(duration_s, v0 / -a)
        x0 = position + rng.uniform(-0.49, 0.49)  # where the axis is, between steps
        end = x0 + u * (v0 * duration_s + 0.5 * a * duration_s * duration_s)
        target = step_target(end)
        if target != position:
            spans.add(x0, u, v0, a, duration_s, position, target, base_s)
            expected.append(base_s + crossing_times(x0, u, v0, a, duration_s, position, target))
            direction = 1 if target > position else -1
            if runs and runs[-1][0] == direction:
                runs[-1] = (direction, runs[-1][1] + abs(target - position))
            else:
                runs.append((direction, abs(target - position)))
        position, base_s = target, base_s + duration_s
    times = spans.solve()
    assert len(runs) > 20 and len(times) == sum(count for _, count in runs) > 1000
    assert np.max(np.abs(times - np.concatenate(expected))) < 1e-12  # (rounding: a cruise is d/v0)
    d = Dictionary(dictionary_data())
    axis = StepAxis(record=True)  # the same spans held by a step axis, sent in runs by direction
    axis.configure(0, False, 25e-6 * CLOCK_HZ, *d.step_prefixes())
    for row, count in zip(spans.rows, spans.counts, strict=True):
        x0, u, v0, a, duration_s, first, direction, base_s = row
        start = round(first - 0.5 * direction)
        axis.span(x0, u, v0, a, duration_s, start, start + int(direction) * count, base_s)
    axis.add(0.0, CLOCK_HZ, 0.0)
    assert np.array_equal(np.asarray(axis.recorded()), times * CLOCK_HZ)
    sent: list[tuple[bytes, int | None, int]] = []
    axis.flush(0.0, True, sent, None)
    by_direction: list[tuple[int, int]] = []
    for message, _, _ in sent:
        for name, params in d.decode(message):
            if name == "set_next_step_dir":
                by_direction.append((1 if params["dir"] else -1, 0))
            elif name == "queue_step":
                direction, count = by_direction[-1]
                by_direction[-1] = (direction, count + params["count"])
    assert by_direction == runs


def test_compression_keeps_every_step_within_the_bound_and_never_late() -> None:
    rng = np.random.default_rng(5)
    max_error = 25e-6 * CLOCK_HZ
    accel = crossing_times(0.0, 80.0, 0.0, 3000.0, 0.2, 0, step_target(80 * 60.0))
    cruise = crossing_times(0.0, 80.0, 600.0, 0.0, 0.1, 0, 80 * 60)
    jitter = np.cumsum(rng.uniform(20e-6, 3e-3, 500))  # irregular raster steps
    points = 1e6 + CLOCK_HZ * np.concatenate([accel, 0.2 + cruise, 0.31 + jitter])
    compressor = StepCompressor(max_error, last_clock=999_000, last_exact=999_000.0)
    runs, done = compressor.compress(points, final=True)
    assert done == len(points)
    last, clocks = 999_000, []
    for run in runs:
        assert 1 <= run.count <= 65535 and -32768 <= run.add <= 32767 and run.interval >= 0
        clocks.append(run_clocks(last, run))
        last = int(clocks[-1][-1])
    error = points - np.concatenate(clocks)
    assert error.min() >= 0.0 and error.max() <= max_error + 1
    assert len(runs) < 60 + len(jitter), "9,600 steps of acceleration and cruise take < 60 runs"


def test_compression_holds_back_a_run_that_may_still_grow() -> None:
    points = 1e6 + 72_000.0 * np.arange(1, 101)
    compressor = StepCompressor(1800.0, last_clock=1_000_000, last_exact=1e6)
    runs, done = compressor.compress(points, final=False)
    assert runs == [] and done == 0
    runs, done = compressor.compress(points, final=True)
    assert done == 100 and len(runs) == 1 and math.isclose(runs[0].interval, 72_000)


@given(st.lists(st.tuples(
    st.floats(-50.0, 50.0), st.floats(-50.0, 50.0), st.sampled_from([0.0, 0.6, -0.8, 1.0]),
    st.sampled_from([(0.0, 3000.0), (80.0, 0.0), (80.0, -1500.0), (3.0, 200.0)]),
    st.floats(0.0, 0.05)), min_size=1, max_size=12),
    st.sampled_from([80.0, 56.6, 400.0]), st.sampled_from([80.0, 13.0]))
@settings(max_examples=150, deadline=None)
def test_a_piece_s_steps_on_each_axis_are_those_of_the_python_it_replaces(
        pieces: list[tuple[float, float, float, tuple[float, float], float]],
        x_per_mm: float, y_per_mm: float) -> None:
    """``piece_steps`` (one compiled call a piece for every axis) queues the spans that the
    schedule's Python made: the whole step ``floor(x0 + u·d + 0.5)`` at the piece's distance,
    a span from where the axis is when that differs, the position carried on; an axis the
    piece does not move is left alone. Solved (``add``), the same clocks to the bit."""
    axes = (StepAxis(record=True), StepAxis(record=True))
    axes[0].steps_per_mm, axes[1].steps_per_mm = x_per_mm, y_per_mm
    positions, spans = [0, 0], (Spans(), Spans())
    base_s = 1.0
    for x_mm, y_mm, ux, (v0, a), rel_s in pieces:
        start, unit = (x_mm, y_mm), (ux, math.sqrt(1.0 - ux * ux))
        if a < 0.0:
            rel_s = min(rel_s, v0 / -a)
        assert off_track(axes, start) == any(
            abs(s * per_mm - p) > 1.0 for s, per_mm, p in zip(start, (x_per_mm, y_per_mm),
                                                              positions, strict=True))
        piece_steps(axes, start, unit, v0, a, rel_s, base_s)
        distance = v0 * rel_s + 0.5 * a * rel_s * rel_s
        for i, per_mm in enumerate((x_per_mm, y_per_mm)):
            if unit[i] == 0.0:
                continue
            x0, u = start[i] * per_mm, unit[i] * per_mm
            target = math.floor(x0 + u * distance + 0.5)
            if target != positions[i]:
                spans[i].add(x0, u, v0, a, rel_s, positions[i], target, base_s)
                positions[i] = target
        base_s += 0.05
    for axis, axis_spans, position in zip(axes, spans, positions, strict=True):
        assert axis.position == position
        assert axis.add(1e6, CLOCK_HZ, 1.0) == axis_spans.total
        assert np.array_equal(np.asarray(axis.recorded()),
                              axis_spans.solve((1e6, CLOCK_HZ, 1.0)))


def test_piece_steps_refuses_what_is_not_a_piece_of_its_axes() -> None:
    axes = (StepAxis(), StepAxis())
    with pytest.raises(ValueError, match="one number per axis"):
        piece_steps(axes, (0.0,), (1.0, 0.0), 10.0, 0.0, 0.1, 0.0)
    with pytest.raises(TypeError, match="StepAxis"):
        piece_steps((axes[0], "y"), (0.0, 0.0), (0.0, 1.0), 10.0, 0.0, 0.1, 0.0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="not finite"):  # (X's steps are not queued either)
        piece_steps(axes, (0.0, math.inf), (0.6, 0.8), 10.0, 0.0, 0.1, 0.0)
    with pytest.raises(ValueError, match="positive"):
        axes[0].steps_per_mm = 0.0
    assert axes[0].position == axes[1].position == 0 and axes[0].add(0.0, 1.0, 0.0) == 0
