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

import itertools
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import replace
from typing import TextIO, cast

import numpy as np

from server.backends.null import NullBackend
from server.config import CoreConfig
from server.errors import CommandError
from server.gcode.interpreter import Interpreter
from server.gcode.plain import PlainRun, lines_read
from server.machine.parts import interpreter_settings, planner_settings
from server.motion.backend import Backend
from server.motion.feed import offer
from server.motion.moves import Action, Move, Output, Position, Sync
from server.motion.planner import MIN_LENGTH_MM, Block, Planner
from server.motion.stepgen import StepGenerator
from server.offline.stats import JobStats

Run = tuple[np.ndarray, np.ndarray, np.ndarray]
"""A plain run's moves as arrays: their targets (a row each), feeds (mm/s), rapid or not."""
OFFLINE_SYNC_BLOCKS = 1024  # no event loop to keep: fewer, larger syncs (the same plan)
READ_CHUNK_CHARS = 1 << 16  # a job file is read this many characters at a time


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
        self._where = [0]  # the number of the last line read
        self._read = lines_read(lines, interpreter, core.protocol.line_limit, self._where)
        self._on_line = on_line
        self._waiting: list[Output] = []  # outputs read not yet queued
        self._waiting_run: Run | None = None  # their arrays, when they are a run's moves
        self.done = False

    def refill(self) -> None:
        """Queue outputs until the planner is full (reading ahead a line, or a run of plain
        lines) or the job ends."""
        if self._waiting:
            self._waiting = self._queue(self._waiting, self._waiting_run)
            if self._waiting:
                return
        if self.done:  # the end of the job, or a refused line: read no further
            return
        planner, on_line, where = self.planner, self._on_line, self._where
        is_full, append = planner.is_full, planner.append
        full = is_full()
        try:
            for item in self._read:
                if on_line is not None:
                    on_line(where[0])
                if isinstance(item, PlainRun):  # (a plan needs no follow action)
                    moves, feeds_mm_s, rapid = item.moves()
                    self._waiting = self._queue(list[Output](moves),
                                                (item.ends, feeds_mm_s, rapid))
                    if self._waiting:
                        return
                    full = is_full()
                    continue
                outputs = item
                index, count = 0, len(outputs)
                if count == 1 and not full and type(outputs[0]) is Move:
                    full, index = append(outputs[0]), 1  # the common line: offer(), inline
                if index < count:
                    self._waiting = self._queue(outputs[index:] if index else outputs)
                    if self._waiting:
                        return
                    full = is_full()
        except CommandError as exc:
            self.stats.error, self.stats.error_line = f"error:{exc.code} {exc.message}", where[0]
        finally:
            self.stats.lines = where[0]
        self.done = True

    def _queue(self, outputs: list[Output], run: Run | None = None) -> list[Output]:
        """Offer ``outputs`` as the live machine does (:func:`~server.motion.feed.offer`) until
        the planner is full; return those left over. Sync requests need no machine here.
        A run's moves (``run``: their targets, feeds and kinds) are appended at once
        (:meth:`~server.motion.planner.Planner.append_run`: the same blocks)."""
        self._waiting_run = None
        if run is not None:
            moves = cast("list[Move]", outputs)  # (a run's: every output is a move)
            taken = 0 if self.planner.is_full() else self.planner.append_run(moves, *run)
            if taken < len(outputs):
                self._waiting_run = (run[0][taken:], run[1][taken:], run[2][taken:])
                return outputs[taken:]
            return []
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
    """The job's extent, lines read and first refused line, without planning (a fraction of
    the time of :func:`estimate`: the bounding box needs no timing).

    Every line is read and interpreted as :func:`estimate` reads it (runs of plain lines at
    once, :func:`~server.gcode.plain.lines_read`); a move joins the extent when the planner
    would keep it (at least ``MIN_LENGTH_MM`` from the last one kept), so the box is the one
    :func:`estimate` gives. Only the extent, ``lines`` and ``error`` are filled in.
    """
    stats = JobStats(count_start=count_start)
    chain, where = tuple(interpreter.position), [0]
    dist, add = math.dist, stats.add_segment
    try:
        for item in lines_read(lines, interpreter, core.protocol.line_limit, where):
            if isinstance(item, PlainRun):
                chain = _run_extent(stats, chain, item.ends)
                continue
            for output in item:
                if type(output) is Move:
                    target = tuple(output.target_mm)
                    if dist(target, chain) >= MIN_LENGTH_MM:
                        add(chain, target)
                        chain = target
    except CommandError as exc:
        stats.error, stats.error_line = f"error:{exc.code} {exc.message}", where[0]
    finally:
        stats.lines = where[0]
    stats.finish()
    return stats


def _run_extent(stats: JobStats, chain: Position, ends: np.ndarray) -> Position:
    """The moves of a plain run (``ends``, a row each) join the extent: at once when each is
    clearly longer than ``MIN_LENGTH_MM`` (the planner keeps them all), else one by one."""
    if not ends.shape[0]:
        return chain
    steps = np.diff(ends, axis=0, prepend=np.asarray([chain]))
    if float(np.sqrt(np.min(np.einsum("ij,ij->i", steps, steps)))) >= 2 * MIN_LENGTH_MM:
        stats.add_path(chain, ends)
        return tuple(ends[-1].tolist())
    for target in map(tuple, ends.tolist()):  # as extent() reads a move alone
        if math.dist(target, chain) >= MIN_LENGTH_MM:
            stats.add_segment(chain, target)
            chain = target
    return chain


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
    """The lines of :func:`file_chunks`, one at a time."""
    return itertools.chain.from_iterable(file_chunks(handle, limit_chars))


def file_chunks(handle: TextIO, limit_chars: int,
                chunk_chars: int = READ_CHUNK_CHARS) -> Iterator[list[str]]:
    """The lines of a text file opened with universal newlines (``\\n``, ``\\r``, ``\\r\\n``),
    without their endings, a list at a time, read ``chunk_chars`` at a time: no single call
    holds the GIL for long, and a line longer than ``limit_chars`` comes out cut to
    ``limit_chars + 1`` characters (enough for the line-length check to refuse it) while the
    rest of it is skipped, never held."""
    cut, carry, skipping = limit_chars + 1, "", False
    while block := handle.read(chunk_chars):
        if skipping:  # the rest of a line too long
            end = block.find("\n")
            if end < 0:
                continue
            block, skipping = block[end + 1 :], False
        lines = (carry + block).split("\n")
        carry = lines.pop()
        if len(carry) > cut:
            lines.append(carry[:cut])
            carry, skipping = "", True
        if lines and max(map(len, lines)) > cut:
            lines = [line[:cut] for line in lines]
        if lines:
            yield lines
    if carry:
        yield [carry]
