"""Plain lines interpreted at once: a job's runs of ``G0``/``G1`` lines read as arrays.

A raster job is millions of lines like ``G1 X12.3 Y4.5 S380``. Read one at a time (parse,
interpret, a :class:`~server.motion.moves.Move` each) a line costs microseconds of Python; a
job's plan reads them in runs instead: :func:`~server.gcode.parser.parse_plain` parses a
chunk of lines at once, and :func:`plain_run` interprets a run of plain lines from the
interpreter's state with numpy, under exactly the conditions of the interpreter's own fast
path (:meth:`Interpreter._fast_line <server.gcode.interpreter.Interpreter>`: G0/G1, axis
words, F, S; G90, G94; with soft limits, every end inside the travel). The first line it
does not take, every line that is not plain and every run shorter than :data:`MIN_RUN` are
read by the one-line path (:func:`lines_read`), which also finds the errors. A run gives the
same moves, positions and modal state as its lines one by one (the same float operations,
in the same order per line); :meth:`PlainRun.moves` gives the very moves the one-line path
gives, without their follow actions (a line's new S, a spindle action the move carries: the
S is the move's own ``s_value`` too), which a plan's time and extent do not depend on.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from server.gcode.modal import G0, G1, MM_PER_INCH, Geometry, ModalState
from server.gcode.parser import check_length, parse_line, parse_plain
from server.motion.moves import Action, ActionName, Move, MoveKind, Output, Position, ToolMode

if TYPE_CHECKING:
    from server.gcode.interpreter import Interpreter

CHUNK_LINES = 4096  # lines parsed at once (bounded memory: a chunk and its arrays)
MIN_RUN = 32  # fewer plain lines in a row are read one by one (a run costs ~30 lines)
_KINDS = (MoveKind.FEED, MoveKind.RAPID)  # by "rapid", False or True
_SPINDLE = ActionName.SPINDLE


@dataclass(slots=True)
class PlainRun:
    """What a run of plain lines did.

    Attributes:
        count: how many lines of the run were read (the next one is the one-line path's).
        moved: per line read, whether it made a move.
        ends: where each move ends (machine mm), one row per line that moved.
        feeds_mm_min: the feed of each line (mm/min); ``rapid`` per line: G0.
        s: the modal S after each line.
        tool_mode: the modal M3/M4/M5 (the same for the whole run).
        s_before, position_before, motion_before, feed_before: the state before it (the
            state after any number of its lines: :meth:`after`).
    """

    count: int
    moved: np.ndarray
    ends: np.ndarray
    feeds_mm_min: np.ndarray
    rapid: np.ndarray
    s: np.ndarray
    tool_mode: ToolMode
    s_before: float
    position_before: Position
    motion_before: int
    feed_before: float

    def moves(self) -> tuple[list[Move], np.ndarray, np.ndarray]:
        """The run's moves without their follow actions (the S changes; a line that only
        changed S gives nothing): what a plan's time and extent depend on; with their feeds
        (mm/s) and whether each is a rapid (their targets are :attr:`ends`, a row each)."""
        moved = self.moved
        rapid = self.rapid[moved]
        speeds = self._speeds_mm_s()[moved]
        moves = list(map(Move, map(tuple, self.ends.tolist()), speeds.tolist(),
                         map(_KINDS.__getitem__, rapid.tolist()),
                         itertools.repeat(self.tool_mode), self.s[moved].tolist()))
        return moves, speeds, rapid

    def _speeds_mm_s(self) -> np.ndarray:
        """Each line's move speed (mm/s) as the one-line path gives it: G0 at infinity."""
        return np.where(self.rapid, math.inf, self.feeds_mm_min / 60.0)

    def outputs(self) -> tuple[list[Output], list[int]]:
        """Every output of the run's lines, in order, and the run's line each comes from:
        what the one-line path gives for each line (a move, with the action of a new S; a
        line that only changed S, that action alone), equal field for field. What a live
        job's span queues."""
        mode, moved, s = self.tool_mode, self.moved.tolist(), self.s.tolist()
        changed = (self.s != _before(self.s, self.s_before)).tolist()
        speeds, kinds = self._speeds_mm_s().tolist(), self.rapid.tolist()
        ends = iter(map(tuple, self.ends.tolist()))
        outputs: list[Output] = []
        lines: list[int] = []
        for line in range(self.count):
            actions = [Action(_SPINDLE, {"mode": mode, "s": s[line]})] if changed[line] else []
            if moved[line]:
                outputs.append(Move(next(ends), speeds[line], _KINDS[kinds[line]], mode, s[line],
                                    None, actions))
            elif actions:
                outputs += actions
            else:
                continue
            lines.append(line)
        return outputs, lines

    def after(self, lines: int) -> tuple[Position, int, float, float]:
        """The position and the modal motion, feed (mm/min) and S after the run's first
        ``lines`` lines (``lines <= count``; 0: before the run)."""
        if not lines:
            return self.position_before, self.motion_before, self.feed_before, self.s_before
        last = lines - 1
        moves = int(np.count_nonzero(self.moved[:lines]))
        position = tuple(self.ends[moves - 1].tolist()) if moves else self.position_before
        return (position, G0 if self.rapid[last] else G1, float(self.feeds_mm_min[last]),
                float(self.s[last]))


def plain_run(geo: Geometry, modal: ModalState, wco: Position, position: Position,
              columns: dict[str, np.ndarray], count: int) -> PlainRun:
    """Interpret a run of ``count`` plain lines (``columns``: each letter's values, NaN
    where a line has none) from this state, up to the first line the interpreter's fast path
    would not take. Pure: the caller commits the state (:meth:`Interpreter.execute_plain`)."""
    if not takes_runs(geo, modal):
        count, columns = 0, {}
    g, f = columns.get("G"), columns.get("F")
    has_g = _has(g, count)
    motion = _filled(np.where(g == 0.0, G0, G1) if g is not None else None, has_g, modal.motion)
    if f is not None:
        f = f * MM_PER_INCH + 0.0 if modal.inches else f + 0.0
    feeds = _filled(f, _has(f, count), modal.feed)
    count = _taken(geo, columns, count, has_g, motion, feeds)
    columns = {letter: values[:count] for letter, values in columns.items()}
    motion, feeds = motion[:count], feeds[:count]
    owns = [_own(columns.get(name), geo.inch_scale[i] if modal.inches else None, wco[i], count)
            for name, i in geo.axis_index.items()]
    if geo.settings.soft_limits and (inside := _inside(geo, owns, position, count)) < count:
        return plain_run(geo, modal, wco, position, columns, inside)  # up to the line outside
    moved, ends = _moves(owns, position, count)
    s_after = _spindle(columns.get("S"), modal.s, count)
    return PlainRun(count, moved, ends, feeds, motion == G0, s_after, modal.tool_mode,
                    modal.s, position, modal.motion, modal.feed)


def _moves(owns: list[tuple[np.ndarray | None, np.ndarray]], position: Position,
           count: int) -> tuple[np.ndarray, np.ndarray]:
    """Which lines move (their end differs from the position, as ``==`` says) and where each
    move ends: an axis the line names at its word, any other where the last move left it
    (the position, not the last word: ``X-0`` at ``X0`` moves nothing and leaves ``0.0``)."""
    moved = np.zeros(count, bool)
    for (own, has), start in zip(owns, position, strict=True):
        ends = _filled(own, has, start)
        moved |= ends != _before(ends, start)
    rows = []
    for (own, has), start in zip(owns, position, strict=True):
        now = _before(_filled(own, has & moved, start), start)
        rows.append((now if own is None else np.where(has, own, now))[moved])
    return moved, np.stack(rows, axis=1)


def _spindle(s: np.ndarray | None, modal_s: float, count: int) -> np.ndarray:
    """The modal S after each line: a line's S where it changes it (``S-0`` after ``S0``
    changes nothing: the S stays ``0.0``)."""
    if s is None:
        return np.full(count, modal_s)
    s, has_s = s + 0.0, ~np.isnan(s)
    changed = has_s & (s != _before(_filled(s, has_s, modal_s), modal_s))
    return _filled(s, changed, modal_s)


def takes_runs(geo: Geometry, modal: ModalState) -> bool:
    """Whether runs are read from this state: not under G91 (it adds up) or G93."""
    return not (modal.inverse_time or modal.incremental)


def _inside(geo: Geometry, owns: list[tuple[np.ndarray | None, np.ndarray]],
            position: Position, count: int) -> int:
    """How many lines from the first end inside the travel (a line with axis words: its
    end, as :meth:`Geometry.inside`), with soft limits on."""
    outside, named = np.zeros(count, bool), np.zeros(count, bool)
    for (own, has), start, low, high in zip(owns, position, geo.low, geo.high, strict=True):
        ends = _filled(own, has, start)
        outside |= ~((low <= ends) & (ends <= high))
        named |= has
    outside &= named
    return int(np.argmax(outside)) if outside.any() else count


def _taken(geo: Geometry, columns: dict[str, np.ndarray], count: int, has_g: np.ndarray,
           motion: np.ndarray, feeds: np.ndarray) -> int:
    """How many lines from the first the fast path takes: its words (:func:`words_taken`),
    a G0/G1 motion, and a feed for G1."""
    refused = ~words_taken(geo.axis_index, columns, count)
    moving = has_g.copy()
    for letter, values in columns.items():
        if letter in geo.axis_index:
            moving |= ~np.isnan(values[:count])
    refused |= (motion != G0) & (motion != G1)
    refused |= (motion == G1) & moving & (feeds <= 0.0)
    return int(np.argmax(refused)) if refused.any() else count


def words_taken(axes: Iterable[str], columns: dict[str, np.ndarray], count: int) -> np.ndarray:
    """Per line, whether the fast path takes its words whatever the state: G0 or G1, axis
    words, F >= 0 and S >= 0 only."""
    taken = np.ones(count, bool)
    for letter, values in columns.items():
        if letter == "G":
            taken &= np.isnan(values[:count]) | (values[:count] == 0.0) | (values[:count] == 1.0)
        elif letter in ("F", "S"):
            taken &= ~(values[:count] < 0.0)
        elif letter not in axes:
            taken &= np.isnan(values[:count])
    return taken


def _has(values: np.ndarray | None, count: int) -> np.ndarray:
    return np.zeros(count, bool) if values is None else ~np.isnan(values[:count])


def _own(values: np.ndarray | None, scale: float | None, offset: float,
         count: int) -> tuple[np.ndarray | None, np.ndarray]:
    """An axis's target on each line that names it (as the fast path: mm + wco)."""
    if values is None:
        return None, np.zeros(count, bool)
    mm = values * scale if scale is not None else values
    return mm + offset, ~np.isnan(values)


def _filled(values: np.ndarray | None, present: np.ndarray, start: float) -> np.ndarray:
    """Per line, the value of the last line at or before it where ``present`` (``start``
    before the first)."""
    if values is None or not present.any():
        return np.full(present.shape[0], start)
    source = np.where(present, np.arange(present.shape[0]), -1)
    np.maximum.accumulate(source, out=source)
    return np.where(source >= 0, values[np.maximum(source, 0)], start)


def _before(values: np.ndarray, start: float) -> np.ndarray:
    """Per line, the value after the line before it (``start`` before the first)."""
    shifted = np.empty_like(values)
    shifted[:1] = start
    shifted[1:] = values[:-1]
    return shifted


@dataclass(slots=True)
class PlainSpan:
    """Lines ``start`` to ``stop`` of a chunk read by :func:`plain_items` (``columns``: the
    chunk's, from :func:`~server.gcode.parser.parse_plain`), to be read as one run.

    Whoever reads it sets ``taken`` (its lines read so far, from ``start``) and ``count``
    (how many of them the interpreter takes as a run, :meth:`Interpreter.execute_plain
    <server.gcode.interpreter.Interpreter.execute_plain>`); a live job's span is read as the
    planner has room (:meth:`GcodeFeed.handle_span <server.machine.feed.GcodeFeed.handle_span>`)
    and keeps the run's outputs between readings (``outputs``, ``lines``: each one's line of
    the run, ``queued``: how many are in the planner), valid while the interpreter's
    ``state`` is the one they left it in. ``hurry``, when given, is asked at each reading:
    True, and it queues one line only (something waits for the next line boundary).
    """

    columns: dict[str, np.ndarray]
    start: int
    stop: int
    taken: int = 0
    count: int = 0
    run: PlainRun | None = None
    first: int = 0  # the line of the span the run begins at
    outputs: list[Output] = field(default_factory=list)
    lines: list[int] = field(default_factory=list)
    queued: int = 0
    state: object = None
    hurry: Callable[[], bool] | None = None  # True: a reading queues one line (see above)

    def read(self, run: PlainRun) -> None:
        """``run`` (from the line after those taken) is what the span reads from now on."""
        self.run, self.first, self.queued = run, self.taken, 0
        self.count = self.taken + run.count
        self.outputs, self.lines = run.outputs()


def plain_items(chunk: list[str], axes: Iterable[str], limit_bytes: int,
                takes_runs: Callable[[], bool]) -> Iterator[int | PlainSpan]:
    """How to read ``chunk`` (lines without their endings): the index of each line to read
    alone, and a :class:`PlainSpan` for each run of at least :data:`MIN_RUN` plain lines (no
    line over ``limit_bytes``) while ``takes_runs()`` (the interpreter's state, asked as the
    reading gets there). A span is given again while part of what the interpreter takes of it
    is still to read (the planner had no room for it); then the line after is read alone (the
    first one the interpreter's fast path did not take), and the run goes on from the next.
    A span the interpreter took none of is read line by line."""
    if not takes_runs():  # (G91 is seldom left: a chunk at a time)
        yield from range(len(chunk))
        return
    plain = parse_plain(chunk)
    taken = plain.plain & words_taken(axes, plain.columns, len(chunk)) & (
        np.fromiter(map(len, chunk), np.int64, len(chunk)) * 4 <= limit_bytes)
    index = 0
    for start, stop in _runs(taken):
        yield from range(index, start)
        index = start
        while index < stop and takes_runs():
            span = PlainSpan(plain.columns, index, stop)
            yield span
            while 0 < span.taken < span.count:
                yield span
            if not span.taken:
                break
            index += span.taken
            if index < stop:  # the line the fast path did not take
                yield index
                index += 1
    yield from range(index, len(chunk))


def lines_read(lines: Iterable[str], interpreter: Interpreter, limit_bytes: int,
               where: list[int]) -> Iterator[PlainRun | list[Output]]:
    """Read ``lines`` through ``interpreter`` (:func:`plain_items`, :data:`CHUNK_LINES` at a
    time): a :class:`PlainRun` for each run of plain lines, the outputs of each other line
    (the one-line path, which raises its :class:`~server.errors.CommandError`); ``where[0]``
    is the number of the last line read (the refused one, on an error). A line over
    ``limit_bytes`` is refused (error 11)."""
    lines, base = iter(lines), 0
    axes, execute = interpreter.settings.axis_names, interpreter.execute
    while chunk := list(itertools.islice(lines, CHUNK_LINES)):
        for item in plain_items(chunk, axes, limit_bytes, interpreter.takes_runs):
            if type(item) is int:
                text = chunk[item]
                where[0] = base + item + 1
                if 4 * len(text) > limit_bytes:  # only such a line may be too long
                    check_length(text, limit_bytes)
                yield execute(parse_line(text))
                continue
            assert isinstance(item, PlainSpan)
            run = interpreter.execute_plain(item.columns, item.start, item.stop)
            item.taken = item.count = run.count
            where[0] = base + item.start + run.count
            if run.count:
                yield run
        base += len(chunk)


def _runs(taken: np.ndarray) -> list[tuple[int, int]]:
    """The runs of at least :data:`MIN_RUN` taken lines: (first, after the last)."""
    edges = np.flatnonzero(np.diff(taken, prepend=False, append=False))
    pairs = edges.reshape(-1, 2).tolist()
    return [(start, stop) for start, stop in pairs if stop - start >= MIN_RUN]
