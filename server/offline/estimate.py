"""Offline runs of the real pipeline: ``motiond estimate`` and the full virtual execution.

Both feed a job through the same parser, interpreter, planner and block-popping policy as the
server (:meth:`StepGenerator.pop_block`), refilling the planner to full before every pop, as a
sender that keeps up would. :func:`iterate_blocks` yields the planned blocks in execution
order and sums their durations; :func:`execute` runs the actual step generator tick by tick on
virtual time with a backend. The two agree to within a tick: the estimate is the execution.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field, replace
from itertools import chain
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from server.backends.base import Backend
from server.backends.null import NullBackend
from server.config import Config, CoreConfig
from server.errors import CommandError
from server.gcode.interpreter import Interpreter
from server.gcode.parser import check_length, parse_line
from server.motion.feed import offer
from server.motion.limits import CRUISE, CUTTING_CODE, DURATION, KIND, LENGTH
from server.motion.moves import Action, Move, MoveKind, Output, Sync
from server.motion.planner import Block, Planner, SettledBlocks
from server.motion.stepgen import StepGenerator
from server.runtime.parts import interpreter_settings, planner_settings

CUTTING = (MoveKind.FEED, MoveKind.ARC, MoveKind.PROBE)
BBOX_BATCH = 4096
OFFLINE_SYNC_BLOCKS = 1024  # no event loop to keep: fewer, larger syncs (the same plan)
SKIP_CHUNK_CHARS = 1 << 16


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
    _points: list[float] = field(default_factory=list, repr=False)  # end points, flat
    _axes: int = field(default=0, repr=False)

    def add(self, block: Block) -> None:
        self.duration_s += block.duration_s
        self.blocks += 1
        move = block.move
        if move is None:
            return
        if move.kind in CUTTING:
            self.cut_mm += block.length_mm
        else:
            self.rapid_mm += block.length_mm
        if block.cruise_mm_s > self.max_speed_mm_s:
            self.max_speed_mm_s = block.cruise_mm_s
        self._add_point(block.start_mm, block.end_mm)

    def add_settled(self, settled: SettledBlocks) -> None:
        """:meth:`add` for many blocks at once, with numpy."""
        rows = settled.rows
        durations, lengths, cutting = rows[DURATION], rows[LENGTH], rows[KIND] == CUTTING_CODE
        self.duration_s += float(np.add.reduce(durations))
        self.blocks += durations.shape[0]
        self.cut_mm += float(np.add.reduce(lengths[cutting]))
        self.rapid_mm += float(np.add.reduce(lengths[~cutting]))  # action blocks: no length
        self.max_speed_mm_s = max(self.max_speed_mm_s, float(np.maximum.reduce(rows[CRUISE])))
        moving = [(start, end) for move, _, start, end, _ in settled.geometry if move is not None]
        if not moving:
            return
        if not self._axes:  # the first move: its start counts too
            self._axes = len(moving[0][0])
            self._points += moving[0][0]
        self._points += chain.from_iterable([end for _, end in moving])
        if len(self._points) >= BBOX_BATCH * self._axes:
            self.finish()

    def _add_point(self, start: tuple[float, ...], end: tuple[float, ...]) -> None:
        points = self._points
        if not self._axes:  # the first move: its start counts too
            self._axes = len(start)
            points += start
        points += end
        if len(points) >= BBOX_BATCH * self._axes:
            self.finish()

    def finish(self) -> None:
        """Fold the collected end points into the bounding box (done in batches, with numpy)."""
        if not self._points:
            return
        points = np.fromiter(self._points, np.float64, len(self._points)).reshape(-1, self._axes)
        self._points.clear()
        low, high = points.min(axis=0).tolist(), points.max(axis=0).tolist()
        if self.bbox_min_mm:
            low = [min(a, b) for a, b in zip(low, self.bbox_min_mm, strict=True)]
            high = [max(a, b) for a, b in zip(high, self.bbox_max_mm, strict=True)]
        self.bbox_min_mm, self.bbox_max_mm = low, high


class _Listener:
    def on_action(self, action: Action) -> None:
        pass

    def on_idle(self) -> None:
        pass

    def on_hold_stopped(self) -> None:
        pass


class _Feeder:
    """Feeds the job's outputs until the planner is full, as a sender that keeps up would.

    A line's outputs may straddle a full planner (the chords of an arc), exactly as the live
    machine waits for room between them. Records the first refused line.
    """

    def __init__(
        self,
        lines: Iterable[str],
        core: CoreConfig,
        stats: JobStats,
        on_line: Callable[[int], None] | None,
        interpreter: Interpreter | None = None,
    ) -> None:
        origin = tuple(0.0 for _ in core.axis_names)
        if interpreter is None:
            interpreter = Interpreter(interpreter_settings(core))
            interpreter.set_position(origin)
        self.interpreter = interpreter
        settings = replace(planner_settings(core), sync_blocks=OFFLINE_SYNC_BLOCKS)
        self.planner = Planner(settings, origin)
        self.stats = stats
        self._lines = enumerate(lines, 1)
        self._line_limit = core.protocol.line_limit
        self._on_line = on_line
        self._waiting: list[Output] = []  # outputs of the current line not yet queued
        self.done = False

    def refill(self) -> None:
        """Queue outputs until the planner is full (reading one line ahead) or the job ends."""
        if self._waiting:
            self._waiting = self._queue(self._waiting)
            if self._waiting:
                return
        if self.done:  # the end of the job, or a refused line: read no further
            return
        planner, stats, on_line = self.planner, self.stats, self._on_line
        execute, is_full, append = self.interpreter.execute, planner.is_full, planner.append
        limit, number, full = self._line_limit, stats.lines, is_full()
        try:
            for number, text in self._lines:  # noqa: B007 - the last number counts
                if on_line is not None:
                    on_line(number)
                if 4 * len(text) > limit:  # only such a line may be too long
                    check_length(text, limit)  # error 11, as the server refuses it
                outputs = execute(parse_line(text))
                if len(outputs) == 1 and type(outputs[0]) is Move and not full:
                    full = append(outputs[0])  # the common line: offer() of one move, inline
                elif outputs:
                    self._waiting = self._queue(outputs)
                    if self._waiting:
                        return
                    full = is_full()
        except CommandError as exc:
            stats.error, stats.error_line = f"error:{exc.code} {exc.message}", number
        finally:
            stats.lines = number
        self.done = True

    def _queue(self, outputs: list[Output]) -> list[Output]:
        """Offer ``outputs`` as the live machine does (:func:`~server.motion.feed.offer`) until
        the planner is full; return those left over. Sync requests need no machine here."""
        index = 0
        while index < len(outputs):
            index = offer(self.planner, outputs, index)
            if index < len(outputs) and type(outputs[index]) is not Sync:
                return outputs[index:]  # the planner is full
            index += 1
        return []


def _pipeline(
    lines: Iterable[str],
    core: CoreConfig,
    backend: Backend,
    stats: JobStats,
    on_line: Callable[[int], None] | None,
    interpreter: Interpreter | None = None,
) -> tuple[_Feeder, StepGenerator]:
    feeder = _Feeder(lines, core, stats, on_line, interpreter)
    steps_per_mm = tuple(axis.steps_per_mm for axis in core.axes.values())
    stepgen = StepGenerator(
        feeder.planner, backend, steps_per_mm, _Listener(), tick_hz=core.stepgen.tick_hz
    )
    stepgen.before_pop = feeder.refill
    return feeder, stepgen


def iterate_blocks(
    lines: Iterable[str],
    core: CoreConfig,
    stats: JobStats,
    on_line: Callable[[int], None] | None = None,
    interpreter: Interpreter | None = None,
) -> Iterator[Block]:
    """Every block of the job in execution order, planned exactly as the server plans them.

    ``interpreter`` reads the job (default: a plain one for ``core``, without module codes;
    :func:`machine_interpreter` gives the one a configured machine uses)."""
    feeder, stepgen = _pipeline(lines, core, NullBackend(), stats, on_line, interpreter)
    while True:
        block = stepgen.pop_block()
        if block is None:
            if feeder.done:
                stats.moves = feeder.planner.moves_appended
                stats.finish()
                return
            continue
        stats.add(block)
        yield block


def estimate(
    lines: Iterable[str],
    core: CoreConfig,
    on_line: Callable[[int], None] | None = None,
    interpreter: Interpreter | None = None,
) -> JobStats:
    """Job time and extent without ticking (fast).

    The same blocks as :func:`iterate_blocks`, popped in settled batches
    (:meth:`Planner.pop_settled`) and summed with numpy instead of one :class:`Block` at a time.
    """
    stats = JobStats()
    feeder = _Feeder(lines, core, stats, on_line, interpreter)
    planner = feeder.planner
    while True:
        feeder.refill()
        settled = planner.pop_settled()
        if settled is not None:
            stats.add_settled(settled)
            continue
        block = planner.pop()  # follow actions left after the last move
        if block is not None:
            stats.add(block)
        elif feeder.done:
            stats.moves = planner.moves_appended
            stats.finish()
            return stats


def execute(
    lines: Iterable[str],
    core: CoreConfig,
    backend: Backend | None = None,
    interpreter: Interpreter | None = None,
) -> JobStats:
    """Run the job through the step generator tick by tick on virtual time."""
    stats = JobStats()
    feeder, stepgen = _pipeline(lines, core, backend or NullBackend(), stats, None, interpreter)
    tick_s = stepgen.tick_s
    ticks = 0
    stepgen.tick(0.0)
    started_tick: int | None = None
    while True:
        feeder.refill()
        if feeder.done:
            stepgen.request_start()
        ticks += 1
        stepgen.tick(ticks * tick_s)
        if started_tick is None and stepgen.state.moving:
            started_tick = ticks - 1
        if feeder.done and stepgen.idle:
            break
    stats.duration_s = (ticks - (started_tick or 0)) * tick_s if started_tick is not None else 0.0
    stats.blocks = stepgen.state.blocks_done
    stats.moves = feeder.planner.moves_appended
    return stats


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


def machine_interpreter(config: Config) -> Interpreter:
    """The interpreter the configured machine would read a job with: its settings and the
    M-codes its modules claim (the modules are built, never started).

    Raises:
        ConfigError: the config is invalid, or two modules claim one code.
    """
    from server.runtime.clock import VirtualClock
    from server.runtime.kernel import Kernel

    return Kernel(config, VirtualClock()).machine.new_interpreter()


def file_lines(handle: TextIO, limit_chars: int) -> Iterator[str]:
    """The lines of a text file opened with universal newlines (``\\n``, ``\\r``, ``\\r\\n``),
    without their endings, read in small pieces: no single call holds the GIL for long, and a
    line longer than ``limit_chars`` comes out cut to ``limit_chars + 1`` characters (enough
    for the line-length check to refuse it) while the rest of it is skipped, never held."""
    while line := handle.readline(limit_chars + 2):  # room for the ending and one more
        if line.endswith("\n"):
            yield line[:-1]
        elif len(line) <= limit_chars:
            yield line  # the last line, without an ending
        else:
            rest = line
            while rest and not rest.endswith("\n"):
                rest = handle.readline(SKIP_CHUNK_CHARS)
            yield line[: limit_chars + 1]


def read_file_lines(path: Path, limit_chars: int) -> list[str]:
    """Every line of a job file (see :func:`file_lines`); call it in a thread."""
    with path.open(errors="replace") as handle:
        return list(file_lines(handle, limit_chars))


# -- the CLI commands -----------------------------------------------------------------------
@contextlib.contextmanager
def collection_paused() -> Iterator[None]:
    """No automatic garbage collection during a one-shot command (``motiond estimate``).

    The pipeline makes no reference cycles (blocks are freed by reference counting as they
    are popped), so a collection finds nothing; but each full one re-scans everything loaded,
    the list of the job's lines among it: 15 % of a 300,000-line raster's estimate.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _read_lines(path: Path) -> list[str]:
    return path.read_text(errors="replace").splitlines()


def _progress(total: int, label: str, enabled: bool) -> tuple[Callable[[int], None], Any]:
    from tqdm import tqdm

    bar = tqdm(
        total=total, unit="line", desc=label, disable=not enabled, leave=False, mininterval=0.2
    )
    last = [0]

    def update(number: int) -> None:
        if number - last[0] >= 2000 or number == total:
            bar.update(number - last[0])
            last[0] = number

    return update, bar


def estimate_command(args: Any, config: Config) -> int:
    """``motiond estimate FILE``."""
    path: Path = args.file
    try:
        lines = _read_lines(path)
    except OSError as exc:
        print(f"motiond: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 1
    show = not args.no_progress and not args.json and sys.stderr.isatty() and len(lines) > 5000
    update, bar = _progress(len(lines), path.name, show)
    with collection_paused():
        stats = estimate(lines, config.core, update if show else None, machine_interpreter(config))
    bar.close()
    if args.json:
        print(json.dumps({"file": str(path), **_public(asdict(stats))}, indent=2))
    else:
        print(describe(path, stats, config.core.axis_names))
    return 1 if stats.error else 0


def _public(fields: dict[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in fields.items() if not key.startswith("_")}


def _count(number: int, noun: str) -> str:
    return f"{number:,} {noun}{'' if number == 1 else 's'}"


def describe(path: Path, stats: JobStats, axis_names: tuple[str, ...]) -> str:
    rows = [
        f"{path}",
        f"  time        {format_duration(stats.duration_s)}",
        f"  cutting     {stats.cut_mm:,.1f} mm",
        f"  rapids      {stats.rapid_mm:,.1f} mm",
        f"  moves       {stats.moves:,} ({_count(stats.blocks, 'planned block')}, "
        f"{_count(stats.lines, 'line')})",
        f"  max speed   {stats.max_speed_mm_s * 60:,.0f} mm/min",
    ]
    if stats.bbox_min_mm:
        extent = "  ".join(
            f"{name} {low:.3f}..{high:.3f}"
            for name, low, high in zip(
                axis_names, stats.bbox_min_mm, stats.bbox_max_mm, strict=True
            )
        )
        rows.append(f"  extent      {extent}")
    if stats.error:
        rows.append(f"  STOPPED at line {stats.error_line}: {stats.error}")
    return "\n".join(rows)


def render_command(args: Any, config: Config) -> int:
    """``motiond render FILE -o OUT``."""
    from server.offline.render import collect, draw

    path: Path = args.file
    output: Path = args.output
    if output.suffix.lower() not in (".svg", ".png"):
        print("motiond: the output must end in .svg or .png", file=sys.stderr)
        return 2
    try:
        lines = _read_lines(path)
    except OSError as exc:
        print(f"motiond: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 1
    stats = JobStats()
    blocks = iterate_blocks(lines, config.core, stats, interpreter=machine_interpreter(config))
    toolpath = collect(blocks, config.core.machine.laser_mode)
    title = f"{path.name} — {format_duration(stats.duration_s)}, {stats.cut_mm:,.0f} mm cut"
    if stats.error:
        title += f" (stopped at line {stats.error_line})"
    draw(toolpath, output, title)
    print(
        f"wrote {output} ({len(toolpath.feed):,} feed and {len(toolpath.rapid):,} rapid segments)"
    )
    if stats.error:
        print(f"  stopped at line {stats.error_line}: {stats.error}", file=sys.stderr)
    return 1 if stats.error else 0
