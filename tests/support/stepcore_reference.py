"""The Klipper backend's step core in numpy: the oracle the compiled core
(``server/backends/klipper/_stepcore.c``) is held to, exactly (tests only).

The compression is the numpy implementation the backend ran before the core was compiled; the
step times are :meth:`~server.backends.klipper.steptimes.Spans.solve`'s arithmetic, one
formula for every piece. The algorithms are explained in the docstrings of
:mod:`server.backends.klipper.stepcompress` and :mod:`server.backends.klipper.steptimes`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from server.backends.klipper.stepcompress import (
    ADD_MAX,
    ADD_MIN,
    MAX_COUNT,
    MAX_TRIES,
    QUADRATIC_DEV,
    WINDOW,
    StepRun,
    run_clocks,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


def windows(
    points: FloatArray, last_clock: int, previous: float, max_error: float
) -> tuple[IntArray, IntArray]:
    """Integer windows ``[lo, hi]`` (relative to ``last_clock``) for each exact step clock."""
    q = points - last_clock
    gaps = np.empty_like(points)
    gaps[0] = points[0] - previous
    np.subtract(points[1:], points[:-1], out=gaps[1:])
    err = np.minimum(max_error, 0.5 * np.maximum(gaps, 0.0))
    hi = np.maximum(np.floor(q), 1.0).astype(np.int64)
    lo = np.ceil(q - err).astype(np.int64)
    lo = np.maximum(np.minimum(lo, hi), 1)
    return lo, hi


def longest_run(lo: IntArray, hi: IntArray, add: int) -> tuple[int, int]:
    """``(count, interval)`` of the longest run from the start that ``add`` allows."""
    m = np.arange(1, len(lo) + 1, dtype=np.int64)
    tri = m * (m - 1) // 2 * add
    interval_lo = np.maximum.accumulate(-((tri - lo) // m))  # ceil((lo - tri) / m)
    interval_hi = np.minimum.accumulate((hi - tri) // m)
    bad = np.flatnonzero(interval_lo > interval_hi)
    count = int(bad[0]) if len(bad) else len(lo)
    if count == 0:
        return 0, 0
    return count, int(interval_hi[count - 1])


def best_run(lo: IntArray, hi: IntArray, max_error: float) -> StepRun:
    """The run reaching furthest over the ``add`` search."""
    min_add, max_add, add = ADD_MIN, ADD_MAX, 0
    best, best_reach, zero = StepRun(0, 0, 0), -1, StepRun(0, 0, 0)
    for _ in range(MAX_TRIES):
        count, interval = longest_run(lo, hi, add)
        if count == len(lo):
            return StepRun(interval, count, add)
        reach = add * (count * (count - 1) // 2) + interval * count
        if count and (reach > best_reach or (reach == best_reach
                                             and interval > best.interval)):
            best, best_reach = StepRun(interval, count, add), reach
            if add == 0:
                zero = best
        m = count + 1  # the first step it misses
        if add * (m * (m - 1) // 2) + interval * m < lo[count]:
            min_add = add + 1  # that step comes too early: more add
        else:
            max_add = add - 1
        if count > 1:
            spread = int(max_error * QUADRATIC_DEV) // (count * count)
            min_add, max_add = max(min_add, add - spread), min(max_add, add + spread)
        if min_add > max_add:
            break
        add = max_add - (max_add - min_add) // 4
    if zero.count and zero.count + zero.count // 16 >= best.count:
        return zero
    return best


def compress(points: FloatArray, last_clock: int, last_exact: float, max_error: float,
             final: bool) -> tuple[list[StepRun], int, int, float, FloatArray]:
    """Runs for a prefix of ``points``, how many they cover, the new last clock and exact
    time, and each covered step's early-ness (ticks)."""
    runs: list[StepRun] = []
    errors: list[FloatArray] = []
    done = 0
    size = WINDOW
    while done < len(points):
        window = points[done:done + size]
        lo, hi = windows(window, last_clock, last_exact, max_error)
        run = best_run(lo, hi, max_error)
        if run.count == len(window) < len(points) - done and size < MAX_COUNT:
            size = min(MAX_COUNT, size * 4)  # it may reach further: look further
            continue
        size = WINDOW
        if not final and done + run.count == len(points):
            break
        runs.append(run)
        clocks = run_clocks(last_clock, run)
        errors.append(window[:run.count] - clocks)
        last_clock = int(clocks[-1])
        last_exact = float(window[run.count - 1])
        done += run.count
    return runs, done, last_clock, last_exact, np.concatenate(errors or [np.empty(0)])


Row = tuple[float, float, float, float, float, float, float, float]


def solve(rows: Sequence[Row], counts: Sequence[int], ref_clock: float = 0.0, hz: float = 1.0,
          ref_s: float = 0.0) -> FloatArray:
    """Every step's time (rows as :class:`~server.backends.klipper.steptimes.Spans` holds
    them), non-decreasing, mapped to ``ref_clock + hz * (t - ref_s)``."""
    count_array = np.array(counts, dtype=np.int64)
    if not count_array.sum():
        return np.empty(0)
    table = np.repeat(np.array(rows, dtype=np.float64).T, count_array, axis=1)
    x0, u, v0, a, duration_s, first, direction, base_s = table
    k = np.arange(len(x0), dtype=np.float64) - np.repeat(
        np.cumsum(count_array) - count_array, count_array)
    boundaries = first + direction * k
    distance = np.maximum((boundaries - x0) / u, 0.0)
    root = np.sqrt(np.maximum(v0 * v0 + 2.0 * a * distance, 0.0))
    times = 2.0 * distance / np.maximum(v0 + root, 1e-300)
    times = np.maximum.accumulate(base_s + np.clip(times, 0.0, duration_s))
    return np.asarray(ref_clock + hz * (times - ref_s), dtype=np.float64)
