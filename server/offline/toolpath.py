"""A job's planned toolpath for the browser: the XY polyline, decimated to a bounded size.

:func:`plan_toolpath` runs a job through the real pipeline
(:func:`server.offline.estimate.iterate_blocks`: parser, interpreter, planner, exactly as the
server plans it) and keeps, per segment, the kind of move, the planned cruise speed and the
laser/spindle power. It is pure and slow (seconds for a large raster): call it in a thread.

Decimation merges consecutive segments that stay within ``tolerance_mm`` of one straight line
and share kind, speed bin and power bin. Whenever the result outgrows its cap the tolerance is
quadrupled and the bins coarsened, and what was kept so far is merged again, so memory and
output stay bounded whatever the job's length. Far over the cap only the shape counts and a
run may fold back on its line, so a raster's back-and-forth lines merge too: the result never
has more than the cap, whatever the path. Units: mm, mm/min, percent of the maximum S.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.motion.moves import MoveKind, ToolMode
from server.offline.estimate import iterate_blocks
from server.offline.stats import JobStats

RAPID, CUT, GAP = 0, 1, 2
TRAVEL_KINDS = frozenset({MoveKind.RAPID, MoveKind.JOG, MoveKind.HOMING})
BASE_TOLERANCE_MM = 0.01
FOLD_LEVEL = 1  # from this level on (over the cap once), a run may fold back on its line
SHAPE_LEVEL = 4  # from this level on, only the shape counts
LEVEL_LIMIT = 40  # tolerance 1.2e22 mm: past any real extent; then pairs are joined


@dataclass(slots=True)
class Segment:
    """One straight piece of the path from the top (mm), with what it does."""

    x0: float
    y0: float
    x1: float
    y1: float
    kind: int  # RAPID, CUT or GAP (a jump that is not drawn)
    speed_mm_min: float
    power_pct: float


@dataclass(slots=True)
class _Run:
    """Consecutive segments merged into one line: ``segment`` runs from the first start to the
    last end; ``t_min``/``t_max`` is the extent covered along the unit direction ``ux, uy``."""

    segment: Segment
    ux: float
    uy: float
    key: tuple[int, int, int]
    t_min: float = 0.0
    t_max: float = 0.0


@dataclass(slots=True)
class Decimator:
    """Merges nearly collinear segments with the same look; see the module docstring.

    At level 0 a run only grows forwards. Once over the cap (:data:`FOLD_LEVEL`) a run also
    folds back: a raster's back-and-forth lines within the tolerance of one line become that
    line, which is what bounds the output whatever the path's shape; past :data:`LEVEL_LIMIT`
    neighbouring segments are joined in pairs. The result never has more than ``cap`` segments.
    """

    cap: int
    level: int = 0
    kept: list[Segment] = field(default_factory=list)
    _run: _Run | None = None
    _shrinking: bool = False

    @property
    def tolerance_mm(self) -> float:
        return BASE_TOLERANCE_MM * 4.0**self.level

    def add(self, segment: Segment) -> None:
        length = math.hypot(segment.x1 - segment.x0, segment.y1 - segment.y0)
        if length < 1e-9:
            return
        run = self._run
        if run is not None:
            end = run.segment
            if abs(end.x1 - segment.x0) > 1e-6 or abs(end.y1 - segment.y0) > 1e-6:
                self._flush()
                self._start(Segment(end.x1, end.y1, segment.x0, segment.y0, GAP, 0.0, 0.0))
                self._flush()
            elif self._extends(run, segment, length):
                end.x1, end.y1 = segment.x1, segment.y1
                along = (end.x1 - end.x0) * run.ux + (end.y1 - end.y0) * run.uy
                run.t_min, run.t_max = min(run.t_min, along), max(run.t_max, along)
                return
            else:
                self._flush()
        self._start(segment)

    def finish(self) -> list[Segment]:
        """The merged segments; coarsens until there are at most ``cap``."""
        self._flush()
        while len(self.kept) > self.cap:
            self._shrink()
        return self.kept

    def _extends(self, run: _Run, segment: Segment, length: float) -> bool:
        """Whether ``segment`` continues the run: the same look (a piece shorter than the
        tolerance once over the cap has no visible look of its own: a raster's step to the
        next line), its end within the tolerance of the run's line, and forwards before the
        fold level."""
        folding = self.level >= FOLD_LEVEL
        if self._key(segment) != run.key and not (folding and length <= self.tolerance_mm):
            return False
        dx, dy = segment.x1 - run.segment.x0, segment.y1 - run.segment.y0
        if abs(dx * run.uy - dy * run.ux) > self.tolerance_mm:
            return False
        along = (segment.x1 - segment.x0) * run.ux + (segment.y1 - segment.y0) * run.uy
        return along > 0.0 or folding

    def _start(self, segment: Segment) -> None:
        length = math.hypot(segment.x1 - segment.x0, segment.y1 - segment.y0) or 1.0
        copy = Segment(
            segment.x0,
            segment.y0,
            segment.x1,
            segment.y1,
            segment.kind,
            segment.speed_mm_min,
            segment.power_pct,
        )
        self._run = _Run(
            copy,
            (segment.x1 - segment.x0) / length,
            (segment.y1 - segment.y0) / length,
            self._key(segment),
            0.0,
            length,
        )

    def _flush(self) -> None:
        if self._run is not None:
            self.kept += _pieces(self._run, self.tolerance_mm)
            self._run = None
            if len(self.kept) > 2 * self.cap and not self._shrinking:
                self._shrink()

    def _key(self, segment: Segment) -> tuple[int, int, int]:
        level = self.level
        if level >= SHAPE_LEVEL:  # far over budget: shape only
            return (GAP, 0, 0) if segment.kind == GAP else (CUT, 0, 0)
        power_levels = max(1, 16 >> level)
        speed_ratio = 1.05 ** (2**level)
        speed_bin = (
            int(math.log(segment.speed_mm_min) / math.log(speed_ratio))
            if segment.speed_mm_min > 0
            else -1
        )
        return (segment.kind, speed_bin, round(segment.power_pct / 100.0 * power_levels))

    def _shrink(self) -> None:
        """Coarsen one level, or join pairs once the tolerance is past any extent."""
        self._shrinking = True
        try:
            if self.level < LEVEL_LIMIT:
                self._coarsen()
            else:
                self.kept = _joined_in_pairs(self.kept)
        finally:
            self._shrinking = False

    def _coarsen(self) -> None:
        previous, self.kept, self._run = self.kept, [], None
        self.level += 1
        for segment in previous:
            self.add(segment)
        if self._run is not None:
            self.kept += _pieces(self._run, self.tolerance_mm)
            self._run = None


def _pieces(run: _Run, tolerance_mm: float) -> list[Segment]:
    """A run as segments: start to end when it only went forwards; when it folded back, the
    line it covers (start, the far ends beyond the tolerance) and then on to where it ended."""
    segment = run.segment
    sx, sy, ex, ey = segment.x0, segment.y0, segment.x1, segment.y1
    points = [(sx, sy)]
    if run.t_min < -tolerance_mm:
        points.append((sx + run.t_min * run.ux, sy + run.t_min * run.uy))
    far = (sx + run.t_max * run.ux, sy + run.t_max * run.uy)
    if math.hypot(far[0] - ex, far[1] - ey) > tolerance_mm:
        points.append(far)
    points.append((ex, ey))
    if len(points) == 2:
        return [segment]
    look = (segment.kind, segment.speed_mm_min, segment.power_pct)
    return [Segment(x0, y0, x1, y1, *look) for (x0, y0), (x1, y1) in itertools.pairwise(points)]


def _joined_in_pairs(segments: list[Segment]) -> list[Segment]:
    """Each pair of neighbours as one segment from the first's start to the second's end."""
    joined = []
    for index in range(0, len(segments) - 1, 2):
        first, second = segments[index], segments[index + 1]
        kind = CUT if CUT in (first.kind, second.kind) else first.kind
        joined.append(
            Segment(first.x0, first.y0, second.x1, second.y1, kind, first.speed_mm_min,
                    max(first.power_pct, second.power_pct))
        )
    if len(segments) % 2:
        joined.append(segments[-1])
    return joined


def plan_toolpath(
    lines: Iterable[str],
    core: CoreConfig,
    max_segments: int,
    interpreter: Interpreter | None = None,
) -> dict[str, Any]:
    """The planned path of a job, as JSON-able arrays (see docs/API.md, ``job.toolpath``),
    read by ``interpreter`` (the machine's, with its module codes; default: a plain one)."""
    stats = JobStats()
    decimator = Decimator(cap=max_segments)
    max_s = 1000.0  # Grbl's $30 (fixed in motiond's settings table)
    end: tuple[float, ...] = ()
    laser_mode = core.machine.laser_mode
    for block in iterate_blocks(lines, core, stats, interpreter=interpreter):
        move = block.move
        if move is None:
            continue
        end = block.end_mm
        on = move.tool_mode is not ToolMode.OFF and move.kind not in TRAVEL_KINDS
        travel = move.kind in TRAVEL_KINDS or (laser_mode and (not on or move.s_value <= 0))
        power = min(100.0, max(0.0, move.s_value / max_s * 100.0)) if on else 0.0
        decimator.add(
            Segment(
                block.start_mm[0],
                block.start_mm[1],
                block.end_mm[0],
                block.end_mm[1],
                RAPID if travel else CUT,
                block.cruise_mm_s * 60.0,
                power,
            )
        )
    segments = decimator.finish()
    return _describe(segments, stats, end, decimator)


def _describe(
    segments: list[Segment], stats: JobStats, end: tuple[float, ...], decimator: Decimator
) -> dict[str, Any]:
    points: list[float] = []
    if segments:
        points += [round(segments[0].x0, 3), round(segments[0].y0, 3)]
    for segment in segments:
        points += [round(segment.x1, 3), round(segment.y1, 3)]
    xs, ys = points[0::2], points[1::2]
    return {
        "segments": len(segments),
        "points": points,
        "kinds": [segment.kind for segment in segments],
        "speeds": [round(segment.speed_mm_min) for segment in segments],
        "powers": [round(segment.power_pct, 1) for segment in segments],
        "bounds": {
            "min": [min(xs, default=0.0), min(ys, default=0.0)],
            "max": [max(xs, default=0.0), max(ys, default=0.0)],
        },
        "end": [round(value, 3) for value in end],
        "duration_s": round(stats.duration_s, 2),
        "cut_mm": round(stats.cut_mm, 1),
        "rapid_mm": round(stats.rapid_mm, 1),
        "max_speed_mm_min": round(stats.max_speed_mm_s * 60.0),
        "blocks": stats.blocks,
        "lines": stats.lines,
        "error": stats.error,
        "error_line": stats.error_line,
        "tolerance_mm": decimator.tolerance_mm,
    }
