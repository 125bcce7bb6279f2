"""Step times to ``queue_step`` runs within a bounded error (pure).

The MCU executes ``queue_step interval count add`` as Klipper's src/stepper.c does: from the
stepper's last step clock ``L``, step ``k`` (0-based) happens at
``L + (k+1)·interval + add·k·(k+1)/2``. A run is valid when every step lands inside its window
``[exact - err, exact]`` (never late, at most ``max_error`` early, and never more than half the
gap to the previous step early, so steps keep their order). For a candidate ``add`` the windows
bound ``interval`` from both sides; a running max/min over the windows gives the longest run
that ``add`` allows (vectorised with numpy). Candidate adds come from least-squares fits of the
exact times over shrinking spans (long runs at constant acceleration fit one ``add``), plus 0
and the previous run's add; the longest run wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

MAX_COUNT = 65535
ADD_MIN, ADD_MAX = -32768, 32767
WINDOW = 1024
"""Most steps considered for one run (bounds the work per run)."""


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
    gaps = np.diff(points, prepend=previous)
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


def _fitted_adds(q: FloatArray) -> list[int]:
    """Adds from least-squares fits of ``q(m) = I·m + A·m(m-1)/2`` over shrinking spans."""
    adds: list[int] = []
    span = len(q)
    while span >= 3:
        m = np.arange(1, span + 1, dtype=np.float64)
        tri = m * (m - 1) / 2
        y = q[:span]
        s_mm, s_mt, s_tt = (m * m).sum(), (m * tri).sum(), (tri * tri).sum()
        s_my, s_ty = (m * y).sum(), (tri * y).sum()
        det = s_mm * s_tt - s_mt * s_mt
        if det > 0:
            add = (s_mm * s_ty - s_mt * s_my) / det
            for value in (math.floor(add), math.ceil(add)):
                clamped = min(ADD_MAX, max(ADD_MIN, value))
                if clamped not in adds:
                    adds.append(clamped)
        span //= 4
    return adds


def best_run(lo: IntArray, hi: IntArray, q: FloatArray, hint_add: int) -> StepRun:
    """The longest run over the candidate adds (ties: the first candidate)."""
    best = StepRun(0, 0, 0)
    for add in [hint_add, 0, *_fitted_adds(q)]:
        count, interval = longest_run(lo, hi, add)
        if count > best.count:
            best = StepRun(interval, count, add)
            if count == len(lo):
                break
    return best


@dataclass(slots=True)
class StepCompressor:
    """Per-stepper compression state: the last step's MCU clock and exact time."""

    max_error: float  # ticks
    last_clock: int = 0
    last_exact: float = 0.0
    last_add: int = 0

    def compress(self, points: FloatArray, final: bool) -> tuple[list[StepRun], int]:
        """Runs for a prefix of ``points`` (exact step clocks, one direction, ascending) and how
        many points they cover. Unless ``final``, a last run that reaches the end of ``points``
        is held back (more steps may extend it)."""
        runs: list[StepRun] = []
        done = 0
        while done < len(points):
            window = points[done:done + WINDOW]
            lo, hi = windows(window, self.last_clock, self.last_exact, self.max_error)
            run = best_run(lo, hi, window - self.last_clock, self.last_add)
            run = StepRun(run.interval, min(run.count, MAX_COUNT), run.add)
            if not final and done + run.count == len(points):
                break
            runs.append(run)
            self.last_clock = int(run_clocks(self.last_clock, run)[-1])
            self.last_exact = float(window[run.count - 1])
            self.last_add = run.add
            done += run.count
        return runs, done
