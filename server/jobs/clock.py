"""A job's plan before it starts (time, extent, fit) and its honest remaining time after.

:func:`plan_job` runs the job file through the offline pipeline
(:func:`server.offline.estimate.estimate`) from the machine's real state: a copy of the live
interpreter (position, work offsets, modal state), soft limits off so that the time of a job is
known whatever its placement; the extent is then checked against the travel
(:func:`server.offline.fit.check_fit`). Call it in a thread.

:class:`JobClock` reads the remaining time from that plan: the planned time of the blocks
the step generator has not finished yet. Between block ends it advances with the motion time
the step generator publishes (which stands still in a hold) times the feed override, bounded by
the current block's planned end (on a Grbl controller downstream, which reports no block
count, the motion time alone); the remaining planned time is then divided by the feed
override, so at 150 % the remaining time drops when the override is raised and then counts
down in real time. Units: seconds, percent.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.jobs.reading import Stopped, until
from server.motion.stepgen import MotionState
from server.offline.estimate import estimate, file_lines
from server.offline.fit import Fit, check_fit


@dataclass(frozen=True, slots=True)
class JobPlan:
    """What a job does from the machine's state when it was planned.

    Attributes:
        duration_s: the planned time at 100 % overrides.
        timeline_s: the planned time at the end of every ``timeline_stride``-th block, in
            execution order (bounded in length, see :meth:`JobStats.timeline`).
        fit: the extent (machine mm) against the travel.
        lines: how many lines were read (all of them, or up to ``error_line``).
        error: the first line the interpreter refuses (``error:N text``), or None.
        error_line: its number.
        placement: the machine's position and work offset the plan was made from.
    """

    duration_s: float
    timeline_s: np.ndarray
    timeline_stride: int
    fit: Fit
    lines: int
    error: str | None
    error_line: int | None
    placement: tuple[tuple[float, ...], tuple[float, ...]]


def plan_job(
    path: Path, core: CoreConfig, interpreter: Interpreter, stop: threading.Event | None = None
) -> JobPlan | None:
    """Plan ``path`` from ``interpreter``'s state (a live copy, soft limits off); blocking I/O
    and CPU: call it in a thread. None when ``stop`` was set before the plan was done (the
    file is read as the plan goes: memory stays bounded whatever its size). Raises OSError
    when the file cannot be read."""
    placement = (tuple(interpreter.position), tuple(interpreter.wco()))
    axes = list(core.axes.values())
    with path.open(errors="replace") as handle:
        lines = file_lines(handle, core.protocol.line_limit)
        try:
            stats = estimate(lines if stop is None else until(lines, stop), core, None,
                             interpreter, timeline=True, count_start=False)  # the job's extent
        except Stopped:
            return None
    fit = check_fit(
        stats.bbox_min_mm, stats.bbox_max_mm, [a.min_mm for a in axes],
        [a.max_mm for a in axes], core.axis_names, placement[1],
    )
    return JobPlan(stats.duration_s, stats.timeline(), stats.timeline_stride, fit, stats.lines,
                   stats.error, stats.error_line, placement)


class JobClock:
    """The remaining time of a running job, from its plan and the motion state."""

    def __init__(self, plan: JobPlan, motion: MotionState, *, counts_blocks: bool = True) -> None:
        """``counts_blocks``: ``motion.blocks_done`` counts executed blocks (not on a Grbl
        controller downstream, whose reports give only the motion time)."""
        self.plan = plan
        self._counts_blocks = counts_blocks
        self._blocks_at_start = motion.blocks_done
        self._motion_time_s = motion.motion_time_s
        self._work_s = 0.0  # planned seconds executed so far (motion time x feed override)

    def remaining_s(self, motion: MotionState, feed_override_pct: float) -> float:
        """Seconds left at the current feed override; stands still while motion does."""
        factor = max(0.01, feed_override_pct / 100.0)
        self._work_s += (motion.motion_time_s - self._motion_time_s) * factor
        self._motion_time_s = motion.motion_time_s
        timeline, total = self.plan.timeline_s, self.plan.duration_s
        if not self._counts_blocks:
            self._work_s = min(self._work_s, total)
            return max(0.0, total - self._work_s) / factor
        done_blocks = max(0, motion.blocks_done - self._blocks_at_start)
        done = min(done_blocks // self.plan.timeline_stride, len(timeline))
        low = float(timeline[done - 1]) if done else 0.0
        high = float(timeline[done]) if done < len(timeline) else total
        self._work_s = min(max(self._work_s, low), high)
        return max(0.0, total - self._work_s) / factor
