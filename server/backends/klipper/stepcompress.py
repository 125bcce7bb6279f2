"""Step times to ``queue_step`` runs within a bounded error (pure).

The MCU executes ``queue_step interval count add`` as Klipper's src/stepper.c does: from the
stepper's last step clock ``L``, step ``k`` (0-based) happens at
``L + (k+1)·interval + add·k·(k+1)/2``. A run is valid when every step lands inside its window
``[exact - err, exact]`` (never late, at most ``max_error`` early, and never more than half the
gap to the previous step early, so steps keep their order). For a candidate ``add`` the windows
bound ``interval`` from both sides; a running max/min over the windows gives the longest run
that ``add`` allows (vectorised with numpy). The ``add`` is searched as Klipper's stepcompress
does: a run that ends because its next step would come too early wants a larger ``add``, one
whose next step would come too late a smaller one; the range narrows by a quarter each try and
never beyond what the error bound allows two quadratic sequences of that length to differ by
(``(6 + 4√2)·max_error / count²``). The run reaching furthest wins, and a run without ``add``
(a shorter message) wins when it covers nearly as many steps. Runs grow up to 65,535 steps: the
window considered grows while the best run fills it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

MAX_COUNT = 65535
ADD_MIN, ADD_MAX = -32768, 32767
WINDOW = 1024
"""Steps considered for one run at first (grown while a run fills it)."""
QUADRATIC_DEV = 11  # (6 + 4√2) rounded down, as Klipper uses
MAX_TRIES = 48


@dataclass(frozen=True, slots=True)
class StepRun:
    """One ``queue_step``: ``count`` steps, first ``interval`` ticks after the last, +``add``."""

    interval: int
    count: int
    add: int


def run_clocks(last_clock: int, run: StepRun) -> IntArray:
    """The MCU clock of every step of ``run`` after a last step at ``last_clock``."""
    k = np.arange(run.count, dtype=np.int64)
    return last_clock + (k + 1) * run.interval + run.add * (k * (k + 1) // 2)


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
    """The run reaching furthest over the ``add`` search (see the module docstring)."""
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


@dataclass(slots=True)
class StepCompressor:
    """Per-stepper compression state: the last step's MCU clock and exact time."""

    max_error: float  # ticks
    last_clock: int = 0
    last_exact: float = 0.0

    def compress(self, points: FloatArray, final: bool) -> tuple[list[StepRun], int]:
        """Runs for a prefix of ``points`` (exact step clocks, one direction, ascending) and how
        many points they cover. Unless ``final``, a last run that reaches the end of ``points``
        is held back (more steps may extend it)."""
        runs: list[StepRun] = []
        done = 0
        size = WINDOW
        while done < len(points):
            window = points[done:done + size]
            lo, hi = windows(window, self.last_clock, self.last_exact, self.max_error)
            run = best_run(lo, hi, self.max_error)
            if run.count == len(window) < len(points) - done and size < MAX_COUNT:
                size = min(MAX_COUNT, size * 4)  # it may reach further: look further
                continue
            size = WINDOW
            if not final and done + run.count == len(points):
                break
            runs.append(run)
            self.last_clock = int(run_clocks(self.last_clock, run)[-1])
            self.last_exact = float(window[run.count - 1])
            done += run.count
        return runs, done
