"""A job's plan before it starts (extent, fit, then time) and its honest remaining time after.

A plan comes in two parts, each read from the job file by the offline pipeline from the
machine's real state (a copy of the live interpreter: position, work offsets, modal state;
soft limits off): :func:`read_fit` finds the extent (:func:`server.offline.estimate.extent`,
about a quarter of the work) and checks it against the travel
(:func:`server.offline.fit.check_fit`), which is all a start needs; :func:`read_plan`
plans the whole job (:func:`server.offline.estimate.estimate`) for its time, and its
extent too. Both are blocking I/O and CPU: the server runs them in processes of their
own (:mod:`server.jobs.planning`).

:class:`JobClock` reads the remaining time from that plan: the planned time of the blocks
the step generator has not finished yet. Between block ends it advances with the motion time
the step generator publishes (which stands still in a hold) times the feed override, bounded by
the current block's planned end (on a Grbl controller downstream, which reports no block
count, the motion time alone); the remaining planned time is then divided by the feed
override, so at 150 % the remaining time drops when the override is raised and then counts
down in real time. Units: seconds, percent.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.jobs.reading import until
from server.motion.motion_state import MotionState
from server.offline.estimate import estimate, extent, file_chunks
from server.offline.fit import Fit, check_fit
from server.offline.stats import JobStats


@dataclass(frozen=True, slots=True)
class JobTiming:
    """How long a job takes from the machine's state when it was planned.

    Attributes:
        duration_s: the planned time at 100 % overrides.
        timeline_s: the planned time at the end of every ``timeline_stride``-th block, in
            execution order (bounded in length, see :meth:`JobStats.timeline`).
    """

    duration_s: float
    timeline_s: np.ndarray
    timeline_stride: int


@dataclass(slots=True)
class JobPlan:
    """What a job does from the machine's state when it was planned.

    Attributes:
        fit: the extent (machine mm) against the travel.
        lines: how many lines were read (all of them, or up to ``error_line``).
        error: the first line the interpreter refuses (``error:N text``), or None.
        error_line: its number.
        placement: the machine's position and work offset the plan was made from.
        timing: the job's time, None until it is known (it takes longer than the fit).
    """

    fit: Fit
    lines: int
    error: str | None
    error_line: int | None
    placement: tuple[tuple[float, ...], tuple[float, ...]]
    timing: JobTiming | None = None

    @property
    def duration_s(self) -> float | None:
        """The planned time at 100 % overrides, None while it is not known."""
        return None if self.timing is None else self.timing.duration_s


def read_fit(
    path: Path, core: CoreConfig, interpreter: Interpreter, stopped: Callable[[], bool]
) -> JobPlan:
    """The extent of ``path`` read from ``interpreter``'s state (a live copy, soft limits off)
    and its fit, without the time. Raises OSError when the file cannot be read, and
    :class:`~server.jobs.reading.Stopped` soon after ``stopped()`` becomes true."""
    placement = (tuple(interpreter.position), tuple(interpreter.wco()))
    with path.open(errors="replace") as handle:
        lines = until(file_chunks(handle, core.protocol.line_limit), stopped)
        stats = extent(lines, core, interpreter, count_start=False)  # the job's own extent
    return _plan(stats, core, placement)


def read_plan(
    path: Path, core: CoreConfig, interpreter: Interpreter, stopped: Callable[[], bool]
) -> JobPlan:
    """Fit and time in one pass (the planned blocks give the extent too). Raises as
    :func:`read_fit`."""
    placement = (tuple(interpreter.position), tuple(interpreter.wco()))
    with path.open(errors="replace") as handle:
        lines = until(file_chunks(handle, core.protocol.line_limit), stopped)
        stats = estimate(lines, core, None, interpreter, timeline=True, count_start=False)
    plan = _plan(stats, core, placement)
    plan.timing = JobTiming(stats.duration_s, stats.timeline(), stats.timeline_stride)
    return plan


def _plan(stats: JobStats, core: CoreConfig,
          placement: tuple[tuple[float, ...], tuple[float, ...]]) -> JobPlan:
    axes = list(core.axes.values())
    fit = check_fit(
        stats.bbox_min_mm, stats.bbox_max_mm, [a.min_mm for a in axes],
        [a.max_mm for a in axes], core.axis_names, placement[1],
    )
    return JobPlan(fit, stats.lines, stats.error, stats.error_line, placement)


class JobClock:
    """The remaining time of a running job, from its timing and the motion state."""

    def __init__(self, timing: JobTiming | None, motion: MotionState, *,
                 counts_blocks: bool = True) -> None:
        """``timing``: the job's, planned from the state the job started in (None until it
        is known: set :attr:`timing` then). ``counts_blocks``: ``motion.blocks_done`` counts
        executed blocks (not on a Grbl controller downstream, whose reports give only the
        motion time)."""
        self.timing = timing
        self._counts_blocks = counts_blocks
        self._blocks_at_start = motion.blocks_done
        self._motion_time_s = motion.motion_time_s
        self._work_s = 0.0  # planned seconds executed so far (motion time x feed override)

    def remaining_s(self, motion: MotionState, feed_override_pct: float) -> float | None:
        """Seconds left at the current feed override; stands still while motion does. None
        while the timing is not known."""
        factor = max(0.01, feed_override_pct / 100.0)
        self._work_s += (motion.motion_time_s - self._motion_time_s) * factor
        self._motion_time_s = motion.motion_time_s
        if self.timing is None:
            return None
        timeline, total = self.timing.timeline_s, self.timing.duration_s
        if not self._counts_blocks:
            self._work_s = min(self._work_s, total)
            return max(0.0, total - self._work_s) / factor
        done_blocks = max(0, motion.blocks_done - self._blocks_at_start)
        done = min(done_blocks // self.timing.timeline_stride, len(timeline))
        low = float(timeline[done - 1]) if done else 0.0
        high = float(timeline[done]) if done < len(timeline) else total
        self._work_s = min(max(self._work_s, low), high)
        return max(0.0, total - self._work_s) / factor
