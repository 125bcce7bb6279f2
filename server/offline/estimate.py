"""Offline runs of the real pipeline: ``motiond estimate`` and the full virtual execution.

Both feed a job through the same parser, interpreter, planner and block-popping policy as the
server (:meth:`StepGenerator.pop_block`), refilling the planner to full before every pop, as a
sender that keeps up would. :func:`iterate_blocks` yields the planned blocks in execution
order and sums their durations; :func:`execute` runs the actual step generator tick by tick on
virtual time with a backend. The two agree to within a tick: the estimate is the execution.

The figures summed are :class:`~server.offline.stats.JobStats`; the ``motiond estimate`` and
``motiond render`` commands are :mod:`server.cli.offline`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from typing import TextIO

from server.backends.null import NullBackend
from server.config import CoreConfig
from server.errors import CommandError
from server.gcode.interpreter import Interpreter
from server.gcode.parser import check_length, parse_line
from server.machine.parts import interpreter_settings, planner_settings
from server.motion.backend import Backend
from server.motion.feed import offer
from server.motion.moves import Action, Move, Output, Sync
from server.motion.planner import MIN_LENGTH_MM, Block, Planner
from server.motion.stepgen import StepGenerator
from server.offline.stats import JobStats

OFFLINE_SYNC_BLOCKS = 1024  # no event loop to keep: fewer, larger syncs (the same plan)
SKIP_CHUNK_CHARS = 1 << 16


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
        self.planner = Planner(settings, interpreter.position)  # the job starts where it is
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
    *,
    timeline: bool = False,
    count_start: bool = True,
) -> JobStats:
    """Job time and extent without ticking (fast).

    The same blocks as :func:`iterate_blocks`, popped in settled batches
    (:meth:`Planner.pop_settled`) and summed with numpy instead of one :class:`Block` at a time.
    ``interpreter`` may carry a live machine's state (position, offsets, modal state: see
    :meth:`Machine.new_interpreter`); the job is planned from its position. ``timeline``
    keeps every block's duration (:meth:`JobStats.timeline`: what a running job's remaining
    time is read from). ``count_start=False`` leaves where the tool starts out of the extent
    (the job's own extent, wherever the tool is when it starts).
    """
    stats = JobStats(keep_timeline=timeline, count_start=count_start)
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


def extent(
    lines: Iterable[str], core: CoreConfig, interpreter: Interpreter, *, count_start: bool = True
) -> JobStats:
    """The job's extent, lines read and first refused line, without planning (in about half
    the time of :func:`estimate`: the bounding box needs no timing).

    Every line is read and interpreted as :func:`estimate` reads it; a move joins the extent
    when the planner would keep it (at least ``MIN_LENGTH_MM`` from the last one kept), so
    the box is the one :func:`estimate` gives. Only the extent, ``lines`` and ``error`` are
    filled in.
    """
    stats = JobStats(count_start=count_start)
    execute, limit = interpreter.execute, core.protocol.line_limit
    chain, number, dist, add = tuple(interpreter.position), 0, math.dist, stats.add_segment
    try:
        for number, text in enumerate(lines, 1):  # noqa: B007 - the last number counts
            if 4 * len(text) > limit:  # only such a line may be too long
                check_length(text, limit)  # error 11, as the server refuses it
            for output in execute(parse_line(text)):
                if type(output) is Move:
                    target = tuple(output.target_mm)
                    if dist(target, chain) >= MIN_LENGTH_MM:
                        add(chain, target)
                        chain = target
    except CommandError as exc:
        stats.error, stats.error_line = f"error:{exc.code} {exc.message}", number
    finally:
        stats.lines = number
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
