"""The planner's intake: moves and actions appended to the window, and its back-pressure.

:class:`PlannerIntake` is the part of :class:`~server.motion.planner.Planner` (a base class of
it) that the interpreter side calls: :meth:`PlannerIntake.append` and
:meth:`PlannerIntake.append_action` stage blocks, and :meth:`PlannerIntake.is_full` /
:meth:`PlannerIntake.has_room` say when a writer must wait and when it may go on (the
hysteresis of back-pressure, :data:`REFILL_FRACTION`). Appending is O(1) plain Python: the
block's length, feed and direction are staged; every ``sync_blocks`` appends (and at
``plan()``) the planner copies the staged blocks into its columns and derives their limits in
a batch. Pure computation (no asyncio, no I/O); units are machine mm, mm/s, mm/s² and seconds.

Kept apart from the planning and popping in :mod:`server.motion.planner` (the step
generator's side) because the two sides meet only in the window's columns: what goes in, at
10,000 moves a second, reads here; how it is planned and taken out reads there. As a base class
its methods are the planner's own (no call goes through another object); its state is the
planner's, created by ``Planner.__init__``.
"""

from __future__ import annotations

import math
from operator import mul, sub
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from server.motion.block import BlockColumns, FloatArray
from server.motion.limits import FEED_OVERRIDE, NO_OVERRIDE, RAPID_OVERRIDE, Limits
from server.motion.moves import Action, Move, MoveKind, Position

if TYPE_CHECKING:
    from collections.abc import Sequence

MIN_LENGTH_MM = 1e-6
"""Moves shorter than this are dropped; the next block starts where the last one ended, so
the skipped displacement is not lost."""
RUN_SLICE = 512
"""Moves of a run appended at once (:meth:`PlannerIntake.append_run`): about what a window
takes at a time (the default 0.5 s of 1 ms blocks), so each of the slice's dozen numpy calls
serves hundreds of moves (those past the window's room are read again at the next call):
``estimate`` of a 200,000-line raster 8 % faster than in slices of 128, of the rig's 2,415-line
raster 12 %."""
REFILL_FRACTION = 16
"""A full window takes more blocks once it has drained 1/16 of its bounds (of ``max_blocks``,
at least one block, and of ``max_planned_s``): see :meth:`PlannerIntake.has_room`."""
_RAPID, _JOG, _HOMING = MoveKind.RAPID, MoveKind.JOG, MoveKind.HOMING

Geometry = tuple[Move | None, list[Action], Position, Position, Position]
"""A waiting block's ``(move, actions, start_mm, end_mm, unit)``, as in :class:`Block`."""


def path_length(delta: Sequence[float]) -> float:
    """The length (mm) of a move of ``delta`` (mm per axis): the square root of the sum of the
    squares, added in axis order, as :meth:`PlannerIntake.append_run` computes a run's with
    numpy: the same floats (``math.hypot`` rounds differently, and one call a move costs as
    much as the rest of a run's arithmetic)."""
    squares = 0.0
    for value in delta:
        squares += value * value
    return math.sqrt(squares)


class PlannerIntake:
    """Appending and back-pressure; see the module docstring."""

    # The planner's state this part reads and writes (set by Planner.__init__).
    moves_appended: int
    position_mm: Position
    _zero: Position
    _chain_mm: Position
    _columns: BlockColumns
    _limits: Limits
    _geometry: list[Geometry]
    _pending: list[Action]
    _dirty: bool
    _time_planned_s: float
    _time_estimate_s: float
    _min_feed_mm_s: float
    _inv_rate: tuple[float, ...]
    _max_blocks: int
    _max_planned_s: float
    _refill_blocks: int
    _refill_s: float

    if TYPE_CHECKING:
        def _sync(self) -> None: ...  # the planner's

    # ------------------------------------------------------------------ appending

    def append(self, move: Move) -> bool:
        """Queue a straight move from the end of the last one to ``move.target_mm``; return
        :meth:`is_full` afterwards.

        A move shorter than :data:`MIN_LENGTH_MM` is dropped; its actions ride on the next block.
        O(1): the block is staged; its limits are derived in batches of ``sync_blocks``.
        """
        self.moves_appended += 1
        start, target = self._chain_mm, move.target_mm
        if type(target) is not tuple:
            target = tuple(target)
        if len(target) != len(start):
            raise ValueError(f"expected {len(start)} coordinates, got {len(target)}")
        if len(start) == 3:  # the common machine, unrolled (the same operations, 3x faster)
            x0, y0, z0 = start
            x1, y1, z1 = target
            delta: Sequence[float] = (x1 - x0, y1 - y0, z1 - z0)
            dx, dy, dz = delta
            length = math.sqrt(dx * dx + dy * dy + dz * dz)  # (path_length, unrolled)
            inverse = 1.0 / length if length >= MIN_LENGTH_MM else 0.0
            unit: tuple[float, ...] = (dx * inverse, dy * inverse, dz * inverse)
        elif len(start) == 2:  # a laser's XY, the same
            x0, y0 = start
            x1, y1 = target
            delta = (x1 - x0, y1 - y0)
            dx, dy = delta
            length = math.sqrt(dx * dx + dy * dy)
            inverse = 1.0 / length if length >= MIN_LENGTH_MM else 0.0
            unit = (dx * inverse, dy * inverse)
        else:
            delta = list(map(sub, target, start))
            length = path_length(delta)
            inverse = 1.0 / length if length >= MIN_LENGTH_MM else 0.0
            unit = tuple([x * inverse for x in delta])
        self.position_mm = target
        if length < MIN_LENGTH_MM:
            self._pending.extend(move.actions)
            return self.is_full()
        self._chain_mm = target
        kind = move.kind
        if kind is _RAPID:
            code, feed = RAPID_OVERRIDE, math.inf
            estimate_s = max(map(mul, map(abs, delta), self._inv_rate))
            estimate_s /= self._limits.rapid_override
        else:
            feed = move.feed_mm_s if move.feed_mm_s > 0.0 else 0.0
            code, scaled = FEED_OVERRIDE, feed * self._limits.feed_override
            if kind is _JOG or kind is _HOMING:
                code, scaled = NO_OVERRIDE, feed
            estimate_s = length / (scaled if scaled > self._min_feed_mm_s else self._min_feed_mm_s)
        self._time_estimate_s += estimate_s
        actions = self._take_pending(move.actions) if self._pending else move.actions
        self._geometry.append((move, actions, start, target, unit))
        self._dirty = True
        columns = self._columns
        if columns.push((length, feed, code, 0.0, estimate_s, *unit)):
            self._sync()
        count = columns.tail - columns.head
        return count >= 2 and (
            count >= self._max_blocks
            or self._time_planned_s + self._time_estimate_s >= self._max_planned_s
        )

    def append_run(self, moves: Sequence[Move], ends: FloatArray, feeds_mm_s: FloatArray,
                   rapid: npt.NDArray[np.bool_]) -> int:
        """:meth:`append` each of ``moves`` (feeds and rapids, each ``target_mm`` a tuple;
        ``ends``, ``feeds_mm_s`` and ``rapid``: their targets, a row each, feeds and kinds) in
        turn until the window is full, with numpy; return how many were taken.

        A job's plain lines, read as a run (:mod:`server.gcode.plain`), planned at once: the
        very blocks, limits and estimates that appending them one by one gives (the same
        float operations, each in the same order), at a fraction of the cost. Taken in
        slices of :data:`RUN_SLICE` (a window takes a few hundred blocks at a time); a slice
        with a move shorter than :data:`MIN_LENGTH_MM` is appended one by one."""
        taken, count = 0, len(moves)
        if ends.shape[1] != len(self._chain_mm):
            raise ValueError(f"expected {len(self._chain_mm)} coordinates, got {ends.shape[1]}")
        while taken < count:
            stop = min(count, taken + RUN_SLICE)
            took = self._append_slice(moves[taken:stop], ends[taken:stop],
                                      feeds_mm_s[taken:stop], rapid[taken:stop])
            taken += took
            if taken < stop or self.is_full():
                break
        return taken

    def _append_slice(self, moves: Sequence[Move], ends: FloatArray, feeds: FloatArray,
                      rapid: npt.NDArray[np.bool_]) -> int:
        count = len(moves)
        deltas = ends - np.vstack((np.asarray([self._chain_mm]), ends[:-1]))
        squares = deltas[:, 0] * deltas[:, 0]  # (path_length's, a move a row)
        for axis in range(1, deltas.shape[1]):
            squares += deltas[:, axis] * deltas[:, axis]
        lengths = np.sqrt(squares)
        if float(lengths.min()) < MIN_LENGTH_MM:
            return self._append_each(moves)
        units = deltas * (1.0 / lengths)[:, None]
        feeds = np.where(feeds > 0.0, feeds, 0.0)
        limits = self._limits
        scaled = feeds * limits.feed_override
        estimates = lengths / np.where(scaled > self._min_feed_mm_s, scaled, self._min_feed_mm_s)
        if rapid.any():
            rapid_s = np.max(np.abs(deltas) * np.asarray(self._inv_rate), axis=1)
            estimates = np.where(rapid, rapid_s / limits.rapid_override, estimates)
        taken, times = self._room_for(estimates)
        rows = np.stack((lengths, np.where(rapid, math.inf, feeds),
                         np.where(rapid, RAPID_OVERRIDE, FEED_OVERRIDE), np.zeros(count),
                         estimates), axis=1)
        self._stage_run(moves[:taken], np.hstack((rows, units))[:taken])
        self._time_estimate_s = float(times[taken - 1])
        return taken

    def _append_each(self, moves: Sequence[Move]) -> int:
        for index, move in enumerate(moves):
            if self.append(move):
                return index + 1
        return len(moves)

    def _room_for(self, estimates: FloatArray) -> tuple[int, FloatArray]:
        """How many blocks with these time estimates :meth:`append` takes (up to the one
        after which :meth:`is_full` holds), and the running sums of the estimates as it adds
        them."""
        columns = self._columns
        held = columns.tail - columns.head + np.arange(1, len(estimates) + 1)
        times = np.cumsum(np.concatenate(([self._time_estimate_s], estimates)))[1:]
        full = (held >= 2) & ((held >= self._max_blocks)
                              | (self._time_planned_s + times >= self._max_planned_s))
        return (int(np.argmax(full)) + 1 if full.any() else len(estimates)), times

    def _stage_run(self, moves: Sequence[Move], rows: FloatArray) -> None:
        """Stage the blocks of a run (``rows``: their columns' input values), as
        :meth:`append` stages one."""
        self.moves_appended += len(moves)
        targets = [move.target_mm for move in moves]  # (the rows of ``ends``)
        actions = [move.actions for move in moves]
        if self._pending:
            actions[0] = self._take_pending(actions[0])
        units = map(tuple, rows[:, 5:].tolist())
        self._geometry += zip(moves, actions, [self._chain_mm, *targets[:-1]], targets, units)  # noqa: B905
        self.position_mm = self._chain_mm = targets[-1]
        self._dirty = True
        if self._columns.push_rows(rows):
            self._sync()

    def append_action(self, action: Action) -> None:
        """Queue a non-motion action in order with motion.

        A follow action rides on the next block; a lead action (``lead_s > 0`` or
        ``stops_motion``) becomes a zero-length block where motion stops, carrying any pending
        follow actions before it.
        """
        if action.lead_s <= 0.0 and not action.stops_motion:
            self._pending.append(action)
            return
        lead_s = max(action.lead_s, 0.0)
        here = self._chain_mm
        self._geometry.append((None, self._take_pending([action]), here, here, self._zero))
        self._time_estimate_s += lead_s
        self._dirty = True
        if self._columns.push((0.0, math.inf, NO_OVERRIDE, lead_s, lead_s, *self._zero)):
            self._sync()

    # ------------------------------------------------------------------ window state

    def __len__(self) -> int:
        """Blocks waiting, counting pending follow actions as one action-only block."""
        return len(self._columns) + (1 if self._pending else 0)

    def is_full(self) -> bool:
        """True when the window holds ``max_blocks`` blocks or ``max_planned_s`` of motion.

        Never full with fewer than two blocks, so a single very long move can always queue.
        """
        columns = self._columns
        count = columns.tail - columns.head
        return count >= 2 and (
            count >= self._max_blocks
            or self._time_planned_s + self._time_estimate_s >= self._max_planned_s
        )

    def has_room(self) -> bool:
        """True when the window has drained :data:`REFILL_FRACTION` of its bounds below them
        (or holds fewer than two blocks); never while :meth:`is_full`.

        The hysteresis of back-pressure: a writer that found the window full is woken when
        this holds, not at every popped block, so it takes lines in batches: one wake-up of
        the writer, one reply and one read of the sender's next lines per batch, not per
        line (a 0.1 mm raster at F6000 on the simulated machine: half of what a line cost
        beyond the tick, ``python -m benchmarks lines``). While lines wait, the window stays
        above 15/16 of its bounds: the blocks are the same, and a block's speeds differ
        only where that much look-ahead is what limits them (a stop longer than 0.47 s of
        motion at the default ``max_planned_s``), as they would for a sender a little slower.
        """
        columns = self._columns
        count = columns.tail - columns.head
        return count < 2 or (
            count <= self._refill_blocks
            and self._time_planned_s + self._time_estimate_s <= self._refill_s
        )

    def planned_time_s(self) -> float:
        """Seconds of queued motion: planned durations, plus a lower bound (the time at the
        requested feed, or at the axes' rates for rapids) for blocks appended since the last
        plan."""
        return self._time_planned_s + self._time_estimate_s

    # ------------------------------------------------------------------ internals

    def _take_pending(self, more: list[Action]) -> list[Action]:
        if not self._pending:
            return list(more)
        actions = self._pending
        actions.extend(more)
        self._pending = []
        return actions
