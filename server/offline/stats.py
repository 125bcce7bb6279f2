"""What a job does: the figures summed from its planned blocks, and a duration as text.

:class:`JobStats` is filled by the offline pipeline (:mod:`server.offline.estimate`) one block
or one settled batch at a time; the CLI (:mod:`server.cli.offline`), the server's jobs and
the toolpath read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import chain

import numpy as np

from server.motion.limits import CRUISE, CUTTING_CODE, DURATION, KIND, LENGTH
from server.motion.moves import MoveKind
from server.motion.planner import Block, SettledBlocks

CUTTING = (MoveKind.FEED, MoveKind.ARC, MoveKind.PROBE)
BBOX_BATCH = 4096
TIMELINE_MARKS = 1 << 16  # a job plan's timeline holds at most this many block end times


@dataclass(slots=True)
class JobStats:
    """What a job does. Times in seconds, distances in mm, speeds in mm/s."""

    duration_s: float = 0.0
    cut_mm: float = 0.0
    rapid_mm: float = 0.0
    moves: int = 0
    blocks: int = 0
    lines: int = 0
    max_speed_mm_s: float = 0.0
    bbox_min_mm: list[float] = field(default_factory=list)
    bbox_max_mm: list[float] = field(default_factory=list)
    error: str | None = None
    error_line: int | None = None
    keep_timeline: bool = field(default=False, repr=False)  # collect every block's duration
    count_start: bool = field(default=True, repr=False)  # the first move's start is in the bbox
    _marks: list[np.ndarray] = field(default_factory=list, repr=False)  # see timeline()
    _mark_count: int = field(default=0, repr=False)
    _stride: int = field(default=1, repr=False)
    _timed_blocks: int = field(default=0, repr=False)
    _timed_s: float = field(default=0.0, repr=False)
    _points: list[float] = field(default_factory=list, repr=False)  # end points, flat
    _axes: int = field(default=0, repr=False)

    def add(self, block: Block) -> None:
        self.duration_s += block.duration_s
        self.blocks += 1
        if self.keep_timeline:
            self._record(np.array([block.duration_s]))
        move = block.move
        if move is None:
            return
        if move.kind in CUTTING:
            self.cut_mm += block.length_mm
        else:
            self.rapid_mm += block.length_mm
        if block.cruise_mm_s > self.max_speed_mm_s:
            self.max_speed_mm_s = block.cruise_mm_s
        self.add_segment(block.start_mm, block.end_mm)

    def add_settled(self, settled: SettledBlocks) -> None:
        """:meth:`add` for many blocks at once, with numpy."""
        rows = settled.rows
        durations, lengths, cutting = rows[DURATION], rows[LENGTH], rows[KIND] == CUTTING_CODE
        self.duration_s += float(np.add.reduce(durations))
        self.blocks += durations.shape[0]
        if self.keep_timeline:
            self._record(np.asarray(durations, dtype=np.float64))
        self.cut_mm += float(np.add.reduce(lengths[cutting]))
        self.rapid_mm += float(np.add.reduce(lengths[~cutting]))  # action blocks: no length
        self.max_speed_mm_s = max(self.max_speed_mm_s, float(np.maximum.reduce(rows[CRUISE])))
        moving = [(start, end) for move, _, start, end, _ in settled.geometry if move is not None]
        if not moving:
            return
        if not self._axes:  # the first move: its start counts too (unless count_start is off)
            self._axes = len(moving[0][0])
            self._points += moving[0][0] if self.count_start else ()
        self._points += chain.from_iterable([end for _, end in moving])
        if len(self._points) >= BBOX_BATCH * self._axes:
            self.finish()

    def timeline(self) -> np.ndarray:
        """With ``keep_timeline``: the planned time (s) at the end of every
        :attr:`timeline_stride`-th block, in order (``timeline()[k - 1]`` is the time when
        ``k * timeline_stride`` blocks have run). At most :data:`TIMELINE_MARKS` entries: the
        stride doubles as a job grows, so a plan's memory is bounded whatever the file's size."""
        if not self._marks:
            return np.zeros(0)
        return np.concatenate(self._marks)

    @property
    def timeline_stride(self) -> int:
        return self._stride

    def _record(self, durations: np.ndarray) -> None:
        """Keep the end times of the blocks whose count is a multiple of the stride."""
        count = durations.shape[0]
        if not count:
            return
        ends = np.cumsum(durations) + self._timed_s
        counts = np.arange(self._timed_blocks + 1, self._timed_blocks + count + 1)
        self._timed_blocks += count
        self._timed_s = float(ends[-1])
        picked = ends[counts % self._stride == 0]
        self._marks.append(picked)
        self._mark_count += picked.shape[0]
        while self._mark_count > TIMELINE_MARKS:  # keep every other mark: the stride doubles
            kept = np.concatenate(self._marks)[1::2]
            self._marks, self._mark_count, self._stride = [kept], kept.shape[0], self._stride * 2

    def add_segment(self, start: tuple[float, ...], end: tuple[float, ...]) -> None:
        """A straight move from ``start`` to ``end`` (mm) joins the extent."""
        points = self._points
        if not self._axes:  # the first move: its start counts too (unless count_start is off)
            self._axes = len(start)
            points += start if self.count_start else ()
        points += end
        if len(points) >= BBOX_BATCH * self._axes:
            self.finish()

    def add_path(self, start: tuple[float, ...], ends: np.ndarray) -> None:
        """Straight moves from ``start`` through each row of ``ends`` (mm) join the extent:
        :meth:`add_segment` of each, at once."""
        if not self._axes:
            self.add_segment(start, tuple(ends[0].tolist()))
        self.finish()
        self._fold(ends)

    def finish(self) -> None:
        """Fold the collected end points into the bounding box (done in batches, with numpy)."""
        if not self._points:
            return
        points = np.fromiter(self._points, np.float64, len(self._points)).reshape(-1, self._axes)
        self._points.clear()
        self._fold(points)

    def _fold(self, points: np.ndarray) -> None:
        low, high = points.min(axis=0).tolist(), points.max(axis=0).tolist()
        if self.bbox_min_mm:
            low = [min(a, b) for a, b in zip(low, self.bbox_min_mm, strict=True)]
            high = [max(a, b) for a, b in zip(high, self.bbox_max_mm, strict=True)]
        self.bbox_min_mm, self.bbox_max_mm = low, high


def format_duration(seconds: float) -> str:
    """``1h 02m 03.4s`` style."""
    if not math.isfinite(seconds):
        return "∞"
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{int(hours)}h {int(minutes):02d}m {secs:04.1f}s"
    if minutes:
        return f"{int(minutes)}m {secs:04.1f}s"
    return f"{secs:.2f}s"
