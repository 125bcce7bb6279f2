"""The look-ahead planner: a bounded window of blocks, junction speeds and trapezoids.

Pure computation (no asyncio, no I/O). Units are machine mm, mm/s, mm/s² and seconds.

The interpreter side calls :meth:`Planner.append` / :meth:`Planner.append_action` and watches
:meth:`Planner.is_full` for back-pressure (a writer that found it full waits until
:meth:`Planner.has_room`: a batch's worth below the bounds): that side is the planner's intake,
:mod:`server.motion.planner_intake` (a base class of :class:`Planner`), which stages each block
in O(1) plain Python. The step generator calls :meth:`Planner.pop` for the next block to run,
and :meth:`Planner.plan` first whenever :meth:`Planner.lookahead_short`: that side is this
module. Every ``sync_blocks`` appends (and at ``plan()``) the staged blocks are copied into the
columns of one growable numpy array and their limits derived in a batch (projected axis rates
and accelerations, nominal speeds, junction limits and node caps).
``plan()`` plans at most ``plan_blocks`` blocks from the head with a handful of numpy
operations (:func:`server.motion.trapezoid.plan_prefix`): the rest of the window enters the
backward pass through one minimum, taken with three array operations, so the plan of those
blocks is the plan of the whole window and no call does Python-level work in proportion to the
window. :class:`~server.motion.block.Block` objects are only built at ``pop()``.

Why ``pop()`` may use a plan made before more blocks were appended: appending only adds
look-ahead, which can only raise the limits, so the old plan (which stops at the old end of the
window) stays feasible; its exit speed becomes the fixed start speed of the next plan.
"""

from __future__ import annotations

import math

import numpy as np

from server.motion.block import Block, BlockColumns, SettledBlocks, unplanned_block
from server.motion.limits import (
    ACCEL,
    CAP,
    DURATION,
    ENTRY,
    ESTIMATE,
    EXIT,
    FEED,
    FEED_OVERRIDE_RANGE,
    KIND,
    LEAD,
    LENGTH,
    NO_OVERRIDE,
    NOMINAL,
    RAPID_OVERRIDE_RANGE,
    UNIT,
    Limits,
    PlannerSettings,
    kind_and_feed,
)
from server.motion.moves import Action, Move, Position
from server.motion.planner_intake import (
    MIN_LENGTH_MM,
    REFILL_FRACTION,
    Geometry,
    PlannerIntake,
    path_length,
)
from server.motion.trapezoid import plan_prefix

__all__ = ["MIN_LENGTH_MM", "Block", "Planner", "PlannerSettings", "SettledBlocks"]

PREALLOCATED_BLOCKS = 16384
GEOMETRY_COMPACT = 1024  # popped blocks' geometry entries dropped at once

_TAKEN: Geometry = (None, [], (), (), ())  # in the geometry list, where a popped block was
_POP_ROWS = DURATION + 1


class Planner(PlannerIntake):
    """The waiting window of blocks, planned with look-ahead from the start speed to a stop.

    ``position_mm`` is the target of the last appended move (machine mm).
    """

    def __init__(self, settings: PlannerSettings, position_mm: Position) -> None:
        self.moves_appended = 0  # every move ever appended (statistics)
        axes = len(settings.max_rate_mm_s)
        self._zero: Position = (0.0,) * axes
        self._columns = BlockColumns(
            UNIT + axes, [LENGTH, FEED, KIND, LEAD, ESTIMATE, *range(UNIT, UNIT + axes)],
            _POP_ROWS, _capacity(settings.max_blocks), settings.sync_blocks,
        )
        self._planned = 0  # blocks from the head covered by the last plan
        self._settled = 0  # ... of which appending more blocks cannot change the speeds
        self._geometry: list[Geometry] = []  # of the blocks from _geometry_head on
        self._geometry_head = 0
        self._pending: list[Action] = []
        self._start_mm_s = 0.0
        self._limits = Limits(self._columns, settings.accel_mm_s2, settings.max_rate_mm_s,
                              settings.junction_deviation_mm, settings.min_feed_mm_s)
        self._dirty = self._head_dirty = False
        self._time_planned_s = self._time_estimate_s = 0.0
        self._use_settings(settings)
        self.position_mm: Position = self._zero
        self._chain_mm: Position = self._zero
        self.set_position(position_mm)

    @property
    def settings(self) -> PlannerSettings:
        """The machine limits; assigning new ones applies to blocks appended from then on."""
        return self._settings

    @settings.setter
    def settings(self, settings: PlannerSettings) -> None:
        self._sync()  # blocks already appended keep the limits they were appended with
        self._use_settings(settings)

    def _use_settings(self, settings: PlannerSettings) -> None:
        if len(settings.max_rate_mm_s) != len(self._zero):
            raise ValueError("new planner settings must keep the number of axes")
        self._settings = settings
        self._columns.sync_every = settings.sync_blocks
        self._min_feed_mm_s = settings.min_feed_mm_s
        self._max_blocks, self._max_planned_s = settings.max_blocks, settings.max_planned_s
        self._refill_blocks = settings.max_blocks - max(1, settings.max_blocks // REFILL_FRACTION)
        self._refill_s = settings.max_planned_s * (1 - 1 / REFILL_FRACTION)
        self._inv_rate = tuple(1.0 / rate for rate in settings.max_rate_mm_s)
        limits = Limits(self._columns, settings.accel_mm_s2, settings.max_rate_mm_s,
                        settings.junction_deviation_mm, settings.min_feed_mm_s)
        limits.feed_override = self._limits.feed_override
        limits.rapid_override = self._limits.rapid_override
        self._limits = limits

    # ------------------------------------------------------------------ planning and popping

    def lookahead_short(self) -> bool:
        """Whether the head may plan differently now that blocks were appended since the last
        plan: the head is past the blocks that plan settled (see
        :func:`~server.motion.trapezoid.plan_window`), or it is unplanned or changed. While
        False the last plan is exactly what a new one would give for the head, so re-planning
        can wait.
        """
        return self._dirty and (self._head_dirty or self._settled <= 0)

    def plan(self) -> None:
        """Re-plan the head of the window (at most ``plan_blocks`` blocks, with the whole
        window's look-ahead) if anything changed since the last plan."""
        if not self._dirty:
            return
        self._dirty = self._head_dirty = False
        self._sync()
        columns = self._columns
        head, tail = columns.head, columns.tail
        self._planned = width = min(tail - head, self._settings.plan_blocks)
        if not width:
            return
        data = columns.data
        stop = head + width
        whole = stop == tail
        window = data[:, head:stop]
        cum, caps = np.empty(width + 1), np.empty(width)
        cum[0] = 0.0
        np.add.accumulate(2.0 * window[ACCEL] * window[LENGTH], out=cum[1:])
        caps[: width - 1] = data[CAP, head + 1 : stop]
        caps[width - 1] = 0.0 if whole else data[CAP, stop]
        end_term = end_cum = float(cum[width])
        if not whole:
            end_term, end_cum = self._rest_of_window(stop, end_cum)
        rows = window[LENGTH], window[ACCEL], window[NOMINAL], window[LEAD], caps, cum
        self._settled = plan_prefix(*rows, end_term, end_cum, whole, self._start_mm_s,
                                    window[ENTRY : DURATION + 1])
        columns.invalidate()
        self._time_planned_s = float(np.add.reduce(window[DURATION]))
        self._time_estimate_s = 0.0 if whole else float(np.add.reduce(data[ESTIMATE, stop:tail]))

    def _rest_of_window(self, stop: int, stop_cum: float) -> tuple[float, float]:
        """What the blocks from column ``stop`` to the tail add to a plan of the blocks before:
        the minimum of ``L[j] + C[j]`` over their nodes up to the window's end (whose cap is 0),
        and ``C`` at the end, ``C`` counted on from ``stop_cum`` at node ``stop``."""
        rest = self._columns.data[:, stop : self._columns.tail]
        running = np.empty(rest.shape[1] + 1)
        running[0] = 0.0
        np.add.accumulate(2.0 * rest[ACCEL] * rest[LENGTH], out=running[1:])
        end_s = float(running[-1])
        lowest = min(float(np.minimum.reduce(rest[CAP] + running[:-1])), end_s)
        return stop_cum + lowest, stop_cum + end_s

    def pop(self) -> Block | None:
        """Commit and remove the head block; its entry and exit speeds are final.

        Plans first only when the head was never planned or the start speed, the overrides or
        the head changed since the last plan; otherwise the last plan stands (it stays feasible,
        see the module docstring; call :meth:`plan` first when :meth:`lookahead_short` to keep
        full look-ahead). With no block waiting, returns an action-only block carrying the
        pending follow actions, or None. The popped block's exit speed becomes the start speed.
        """
        columns = self._columns
        if columns.head == columns.tail:  # (not len(columns), without a call: once a block)
            return self._pop_pending()
        if self._head_dirty or self._planned <= 0:
            self._dirty = True
            self.plan()
        (length, _, _, lead, accel, _, nominal, _, entry, cruise, exit_, ramp1, flat, ramp2,
         duration) = columns.pop_front()  # fmt: skip
        geometry, head = self._geometry, self._geometry_head
        move, actions, start, end, unit = geometry[head]
        geometry[head] = _TAKEN  # released now, not with a window's worth at the compaction
        self._geometry_head = head = head + 1
        if head >= GEOMETRY_COMPACT and 2 * head >= len(geometry):  # (_drop_geometry(1): a
            self._drop_geometry(0)  # call only when it compacts)
        self._planned -= 1
        self._settled -= 1
        self._start_mm_s = exit_
        self._time_planned_s -= duration
        if columns.head == columns.tail:
            self._clear_window()
        if move is None:
            nominal = accel = 0.0
        return Block(move, actions, start, end, unit, length, nominal, accel,
                     entry, cruise, exit_, ramp1, flat, ramp2, lead, duration)  # fmt: skip

    def final_count(self) -> int:
        """How many blocks from the head the last plan made final: what as many :meth:`pop`
        calls would give with no append in between (the settled blocks; all planned ones
        while nothing was appended since the plan); 0 when the head needs a plan first
        (:meth:`pop` plans it). Their numbers: :meth:`final_rows`; :meth:`drop_head`
        removes those taken."""
        if self._head_dirty or self._planned <= 0:
            return 0
        return max(0, self._settled if self._dirty else self._planned)

    def final_rows(self, first: int, count: int) -> tuple[list[list[float]], list[Geometry]]:
        """The numbers (as :meth:`pop` reads them: the rows up to the duration) and the
        geometry of ``count`` of those blocks from the ``first`` (0: the head), left in
        place."""
        columns, head = self._columns, self._columns.head + first
        rows = columns.data[:_POP_ROWS, head : head + count].T.tolist()
        geometry = self._geometry_head + first
        return rows, self._geometry[geometry : geometry + count]

    def drop_head(self, rows: list[list[float]]) -> None:
        """Remove the head blocks whose numbers are ``rows`` (the first :meth:`final_rows`
        gave, in order), as as many :meth:`pop` calls would."""
        count = len(rows)
        if not count:
            return
        geometry, head = self._geometry, self._geometry_head
        geometry[head : head + count] = [_TAKEN] * count
        self._drop_geometry(count)
        self._planned -= count
        self._settled -= count
        self._start_mm_s = rows[-1][EXIT]
        planned_s = self._time_planned_s
        for row in rows:  # one at a time, as pop() does: the same float
            planned_s -= row[DURATION]
        self._time_planned_s = planned_s
        if self._columns.drop_front(count):
            self._clear_window()

    def pop_settled(self) -> SettledBlocks | None:
        """Commit and remove the head and every block after it that the last plan settled, at
        once; None with no block waiting (pending follow actions stay for :meth:`pop`).

        Re-plans first when :meth:`lookahead_short`. The blocks are exactly what as many
        :meth:`pop` calls would give, with or without appends in between: settled blocks never
        need a re-plan. For offline runs, which need the numbers but no :class:`Block`.
        """
        columns = self._columns
        if not len(columns):
            return None
        if self._head_dirty or self._planned <= 0 or self.lookahead_short():
            self._dirty = True
            self.plan()
        count = max(self._settled, 1)
        rows = columns.pop_front_many(count)
        geometry = self._take_geometry(count)
        self._planned -= count
        self._settled -= count
        self._start_mm_s = float(rows[EXIT, -1])
        self._time_planned_s -= float(np.add.reduce(rows[DURATION]))
        if not len(columns):
            self._clear_window()
        return SettledBlocks(rows, geometry)

    def flush(self) -> list[Action]:
        """Drop every waiting block and pending action (halt); return the dropped actions.

        ``position_mm`` is stale afterwards: call :meth:`set_position` with where motion stopped.
        """
        waiting = self._geometry[self._geometry_head :]
        dropped = [action for _, actions, _, _, _ in waiting for action in actions]
        dropped += self._pending
        self._geometry, self._geometry_head = [], 0
        self._pending = []
        self._clear_window()
        self._start_mm_s = 0.0
        return dropped

    def set_position(self, position_mm: Position) -> None:
        """Set where the next move starts (machine mm); only with no block waiting."""
        if len(self._columns):
            raise RuntimeError("set_position while blocks are waiting; flush first")
        if len(position_mm) != len(self._zero):
            raise ValueError(f"expected {len(self._zero)} coordinates, got {len(position_mm)}")
        self.position_mm = self._chain_mm = tuple(float(x) for x in position_mm)

    def set_start_speed(self, speed_mm_s: float) -> None:
        """Entry speed (mm/s) of the next popped block: the speed the executing block ends with.

        ``pop()`` sets it to the popped block's exit speed; call this only to change that.
        """
        speed_mm_s = max(float(speed_mm_s), 0.0)
        if speed_mm_s != self._start_mm_s:
            self._start_mm_s = speed_mm_s
            self._dirty = self._head_dirty = True

    def set_overrides(self, feed: float = 1.0, rapid: float = 1.0) -> None:
        """Scale nominal speeds: feed moves by ``feed`` (0.1-2.0, still capped by the axes'
        max rates), rapids by ``rapid`` (0.25-1.0). Values are clamped to those ranges. Applies
        to waiting and future blocks; jog and homing moves are not scaled."""
        feed = min(max(feed, FEED_OVERRIDE_RANGE[0]), FEED_OVERRIDE_RANGE[1])
        rapid = min(max(rapid, RAPID_OVERRIDE_RANGE[0]), RAPID_OVERRIDE_RANGE[1])
        limits = self._limits
        if (feed, rapid) == (limits.feed_override, limits.rapid_override):
            return
        self._sync()
        limits.feed_override, limits.rapid_override = feed, rapid
        limits.renominate()
        self._columns.invalidate()
        self._dirty = self._head_dirty = True

    # ------------------------------------------------------------------ feed-hold remainders

    def make_block(
        self, start_mm: Position, end_mm: Position, move: Move | None, actions: list[Action]
    ) -> Block:
        """Build an unplanned block from ``start_mm`` to ``end_mm`` (speeds and times zero)."""
        start, end = tuple(start_mm), tuple(end_mm)
        delta = [e - s for e, s in zip(end, start, strict=True)]
        length = path_length(delta)
        if length < MIN_LENGTH_MM or move is None:
            return unplanned_block(move, actions, start, end, self._zero)
        unit = tuple([x / length for x in delta])
        accel, nominal = self._limits.of_direction(unit, move)
        return unplanned_block(move, actions, start, end, unit, length, nominal, accel)

    def insert_front(self, block: Block) -> None:
        """Put a block (a remainder after a feed hold) back at the head; it starts from rest.

        A zero-length block keeps its ``lead_s``; motion stays at rest through it.
        """
        if block.move is None or block.length_mm < MIN_LENGTH_MM:
            inputs = (0.0, math.inf, NO_OVERRIDE, block.lead_s, 0.0, *self._zero)
        else:
            kind, feed = kind_and_feed(block.move)
            inputs = (block.length_mm, feed, kind, 0.0, 0.0, *block.unit)
        self._sync()  # derive the limits of staged blocks first: push_front syncs raw inputs
        columns = self._columns
        head = columns.push_front(inputs)
        limits = self._limits
        limits.derive(head, head + 1)
        limits.derive_junctions(head + 1, min(head + 2, columns.tail))
        limits.derive_caps(head, min(head + 2, columns.tail))
        data = columns.data
        data[ESTIMATE, head] = block.lead_s + block.length_mm / data[NOMINAL, head]
        columns.invalidate()
        geometry = (block.move, block.actions, block.start_mm, block.end_mm, block.unit)
        if self._geometry_head:
            self._geometry_head -= 1
            self._geometry[self._geometry_head] = geometry
        else:
            self._geometry.insert(0, geometry)
        self._start_mm_s = 0.0
        self._dirty = self._head_dirty = True
        self._time_estimate_s += data[ESTIMATE, head]

    # ------------------------------------------------------------------ internals

    def _sync(self) -> None:
        """Copy staged blocks into the columns and derive their limits, all at once."""
        columns = self._columns
        first = columns.sync()
        if first < columns.tail:
            self._limits.derive(first, columns.tail)
            self._limits.derive_caps(first, columns.tail)

    def _take_geometry(self, count: int) -> list[Geometry]:
        """Remove the geometry of ``count`` blocks from the head and return it."""
        geometry, head = self._geometry, self._geometry_head
        taken = geometry[head : head + count]
        geometry[head : head + count] = [_TAKEN] * count
        self._drop_geometry(count)
        return taken

    def _drop_geometry(self, count: int) -> None:
        """Forget the geometry of ``count`` blocks from the head (already replaced by
        ``_TAKEN``): a slice of a list is cheaper than popping a deque one by one; the list
        drops its head once it is as long as the rest (amortised O(1) a block, at most a
        window's pointers moved at once)."""
        head = self._geometry_head + count
        if head >= GEOMETRY_COMPACT and 2 * head >= len(self._geometry):
            del self._geometry[:head]
            head = 0
        self._geometry_head = head

    def _pop_pending(self) -> Block | None:
        if not self._pending:
            return None
        here = self._chain_mm
        actions, self._pending = self._pending, []
        return unplanned_block(None, actions, here, here, self._zero)

    def _clear_window(self) -> None:
        self._columns.clear()
        self._geometry, self._geometry_head = [], 0
        self._planned = self._settled = 0
        self._dirty = self._head_dirty = False
        self._time_planned_s = self._time_estimate_s = 0.0


def _capacity(max_blocks: int) -> int:
    """Columns to allocate at first: room for a full window twice over (so the first stream
    does not grow the array while it runs), within reason; a bigger window still grows it."""
    capacity = 256
    while capacity < 2 * max_blocks and capacity < PREALLOCATED_BLOCKS:
        capacity *= 2
    return capacity
