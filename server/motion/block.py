"""One committed block: a straight move with its trapezoidal speed profile, or an action block.

This is what the planner hands to the step generator. Units: positions in machine mm
(absolute, one value per configured axis), speeds in mm/s along the path, accelerations in
mm/s² along the path, times in seconds measured from the start of the block.

A block's motion has three phases: a first ramp from ``entry_mm_s`` to ``cruise_mm_s`` lasting
``accel_s``, a cruise at ``cruise_mm_s`` lasting ``cruise_s``, and a last ramp from
``cruise_mm_s`` to ``exit_mm_s`` lasting ``decel_s``. Normally the first ramp accelerates and the
last one decelerates; when an override lowered the nominal speed below the speed motion already
has, the first ramp decelerates instead (at the same rate ``accel_mm_s2``). A zero-length block
(``move`` is None) carries actions only and stands still for ``lead_s`` (a dwell) or no time.

:class:`BlockColumns` is the planner's storage for the blocks still waiting: their numbers as
columns of one numpy array, so a re-plan is a handful of array operations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from server.motion.moves import Action, Move, Position

FloatArray = npt.NDArray[np.float64]

READ_CHUNK = 32
"""Columns converted to Python floats at once by :meth:`BlockColumns.column`."""


@dataclass(slots=True)
class Block:
    """One planned straight move, or an action-only block (``move`` is None).

    Attributes:
        move: the move this block executes, or None for an action-only block.
        actions: actions run when motion reaches the START of this block, in order.
        start_mm, end_mm: where the block starts and ends (machine mm).
        unit: direction of travel, a unit vector (all zeros for a zero-length block).
        length_mm: path length in mm.
        nominal_mm_s: the speed the block cruises at when it has room (feed limited by the
            axes' max rates projected on the direction, overrides applied).
        accel_mm_s2: the acceleration along the path (axes' limits projected on the direction).
        entry_mm_s, cruise_mm_s, exit_mm_s: speeds at the start, plateau and end.
        accel_s, cruise_s, decel_s: durations of the first ramp, the cruise and the last ramp.
        lead_s: time the block stands still (a dwell), zero for motion blocks.
        duration_s: ``accel_s + cruise_s + decel_s + lead_s``.
    """

    move: Move | None
    actions: list[Action]
    start_mm: Position
    end_mm: Position
    unit: Position
    length_mm: float
    nominal_mm_s: float
    accel_mm_s2: float
    entry_mm_s: float
    cruise_mm_s: float
    exit_mm_s: float
    accel_s: float
    cruise_s: float
    decel_s: float
    lead_s: float
    duration_s: float

    @property
    def motion_s(self) -> float:
        """Seconds of motion (the three phases, without the lead time)."""
        return self.accel_s + self.cruise_s + self.decel_s

    def speed_at(self, t_s: float) -> float:
        """Speed in mm/s at ``t_s`` seconds after the start of the block (clamped to the block)."""
        t1 = self.accel_s
        if t_s < t1:
            if t_s <= 0.0:
                return self.entry_mm_s
            return self.entry_mm_s + (self.cruise_mm_s - self.entry_mm_s) * (t_s / t1)
        t_s -= t1
        if t_s < self.cruise_s:
            return self.cruise_mm_s
        t_s -= self.cruise_s
        t3 = self.decel_s
        if t_s < t3:
            return self.cruise_mm_s + (self.exit_mm_s - self.cruise_mm_s) * (t_s / t3)
        return self.exit_mm_s

    def distance_at(self, t_s: float) -> float:
        """Millimetres travelled along the block at ``t_s`` seconds after its start.

        Analytic (the integral of :meth:`speed_at`), clamped to ``[0, length_mm]``; it is exactly
        ``length_mm`` once the motion phases are over.
        """
        if t_s <= 0.0:
            return 0.0
        entry, cruise, t1 = self.entry_mm_s, self.cruise_mm_s, self.accel_s
        if t_s >= t1 + self.cruise_s + self.decel_s:
            return self.length_mm
        if t_s < t1:
            done = 0.5 * t_s * (entry + self.speed_at(t_s))
            return min(done, self.length_mm)
        done = 0.5 * t1 * (entry + cruise)
        t_s -= t1
        if t_s < self.cruise_s:
            return min(done + cruise * t_s, self.length_mm)
        done += cruise * self.cruise_s
        t_s -= self.cruise_s
        if t_s < self.decel_s:
            speed = cruise + (self.exit_mm_s - cruise) * (t_s / self.decel_s)
            return min(done + 0.5 * t_s * (cruise + speed), self.length_mm)
        return self.length_mm

    def position_at(self, t_s: float) -> Position:
        """Machine position (mm) at ``t_s`` s after the start; exactly ``end_mm`` at the end."""
        distance = self.distance_at(t_s)
        if distance >= self.length_mm:
            return self.end_mm
        return tuple(s + u * distance for s, u in zip(self.start_mm, self.unit, strict=True))


@dataclass(slots=True)
class SettledBlocks:
    """Blocks committed at once (:meth:`~server.motion.planner.Planner.pop_settled`), for
    offline runs that need only their numbers.

    Attributes:
        rows: the planner's rows up to the duration (see the row names in
            :mod:`server.motion.planner`), one column per block, in execution order.
        geometry: per block, ``(move, actions, start_mm, end_mm, unit)`` as in :class:`Block`.
    """

    rows: FloatArray
    geometry: list[tuple[Move | None, list[Action], Position, Position, Position]]


class BlockColumns:
    """The per-block numbers of a window of blocks, one column per block, rows by quantity.

    The ``input_rows`` are given when a block is pushed; the other rows are derived and planned
    by the owner. Pushing only stages the values in a list (O(1), no numpy call), and a run's
    rows pushed at once stay an array (not a list and back); :meth:`sync` copies staged
    columns into the array in one operation and says which columns are new.
    Columns ``head .. tail-1`` are the window; the array grows by doubling and is compacted when
    the window has drifted to its end.

    Reading one column at a time from numpy is slow, so :meth:`column` converts the first
    ``read_rows`` rows of :data:`READ_CHUNK` columns to Python floats at once and serves reads
    from that copy until the owner writes to the array and calls :meth:`invalidate`.
    """

    def __init__(
        self,
        rows: int,
        input_rows: list[int],
        read_rows: int,
        capacity: int = 256,
        sync_every: int = 128,
    ) -> None:
        self.data: FloatArray = np.zeros((rows, capacity))
        self.input_rows = input_rows
        self.read_rows = read_rows
        self.sync_every = sync_every
        self.head = 0
        self.tail = 0  # including staged columns
        self._synced = 0
        self._staged: list[float] = []  # the values of the columns pushed one by one since
        self._segments: list[FloatArray] = []  # ... the staged columns before them, as rows
        # (rows of data, positions in a column's values) for each run of consecutive input rows
        self._runs: list[tuple[slice, slice]] = []
        start = 0
        for end in range(1, len(input_rows) + 1):
            if end == len(input_rows) or input_rows[end] != input_rows[end - 1] + 1:
                self._runs.append((slice(input_rows[start], input_rows[end - 1] + 1),
                                   slice(start, end)))
                start = end
        self._read: list[list[float]] = []  # columns _read_start .. as Python lists
        self._read_start = 0

    def __len__(self) -> int:
        return self.tail - self.head

    def push(self, values: tuple[float, ...]) -> bool:
        """Stage a column given by its ``input_rows`` values; True once ``sync_every`` columns
        are staged (time the owner synced)."""
        self._staged += values
        self.tail += 1
        return self.tail - self._synced >= self.sync_every

    def push_rows(self, rows: FloatArray) -> bool:
        """:meth:`push` each row of ``rows`` (a column's ``input_rows`` values each), at once
        (kept as they are until :meth:`sync`; the caller does not change them)."""
        if self._staged:
            self._segments.append(self._staged_rows())
        self._segments.append(rows)
        self.tail += rows.shape[0]
        return self.tail - self._synced >= self.sync_every

    def _staged_rows(self) -> FloatArray:
        """The columns pushed one by one since the last segment, as rows; none staged now."""
        staged, self._staged = self._staged, []
        return np.fromiter(staged, np.float64, len(staged)).reshape(-1, len(self.input_rows))

    def push_front(self, values: tuple[float, ...]) -> int:
        """Put a column given by its ``input_rows`` values before the head; return its index."""
        self.sync()
        if self.head == 0:
            self._relocate(front=1)
        self.head -= 1
        self.data[self.input_rows, self.head] = values
        self._read = []
        return self.head

    def sync(self) -> int:
        """Copy staged columns into the array; return the index of the first new column.

        Afterwards ``data[:, head:tail]`` is the whole window.
        """
        if not self._staged and not self._segments:
            return self.tail
        if self.tail > self.data.shape[1]:
            self._relocate(front=0)
        first = self._synced
        segments = self._segments
        if self._staged:
            segments.append(self._staged_rows())
        columns = (segments[0] if len(segments) == 1 else np.concatenate(segments)).T
        for rows, values in self._runs:
            self.data[rows, first : self.tail] = columns[values]
        self._synced = self.tail
        self._segments = []
        return first

    def window(self) -> FloatArray:
        """The window as a view of shape (rows, blocks); call :meth:`sync` first."""
        return self.data[:, self.head : self.tail]

    def column(self, index: int) -> list[float]:
        """The first ``read_rows`` values of synced column ``index``, as Python floats."""
        offset = index - self._read_start
        if not 0 <= offset < len(self._read):
            stop = min(index + READ_CHUNK, self._synced)
            self._read = self.data[: self.read_rows, index:stop].T.tolist()
            self._read_start, offset = index, 0
        return self._read[offset]

    def invalidate(self) -> None:
        """Forget the Python copy: the owner wrote to columns that may have been read."""
        self._read = []

    def pop_front(self) -> list[float]:
        """Remove the head column (already synced); return its first ``read_rows`` values."""
        head = self.head
        offset, read = head - self._read_start, self._read  # (column(), without a call while
        values = read[offset] if 0 <= offset < len(read) else self.column(head)  # it is read)
        self.head = head = head + 1
        if head == self.tail:
            self.clear()
        return values

    def drop_front(self, count: int) -> bool:
        """Remove ``count`` columns from the head (already synced); True when that emptied
        the window."""
        self.head += count
        if self.head == self.tail:
            self.clear()
            return True
        return False

    def pop_front_many(self, count: int) -> FloatArray:
        """Remove ``count`` columns from the head (already synced); return a copy of their first
        ``read_rows`` rows."""
        values = self.data[: self.read_rows, self.head : self.head + count].copy()
        self.head += count
        if self.head == self.tail:
            self.clear()
        return values

    def clear(self) -> None:
        """Empty the window."""
        self.head = self.tail = self._synced = 0
        self._staged, self._segments = [], []
        self._read = []

    def _relocate(self, front: int) -> None:
        """Move the synced columns to start at ``front``, growing the array when over half full."""
        head, synced, capacity = self.head, self._synced, self.data.shape[1]
        data = self.data
        needed = self.tail - head + front
        while needed > capacity // 2:
            capacity *= 2
        if capacity != data.shape[1]:
            data = np.zeros((data.shape[0], capacity))
        if data is self.data and front + synced - head > head:  # overlapping: numpy minds it
            data[:, front : front + synced - head] = data[:, head:synced]
        else:  # row by row, which numpy sees cannot overlap: no temporary copy of the window
            for target, source in zip(data, self.data, strict=True):
                target[front : front + synced - head] = source[head:synced]
        self.data = data
        self._read = []
        shift = front - head
        self.head, self.tail, self._synced = head + shift, self.tail + shift, synced + shift


def unplanned_block(
    move: Move | None,
    actions: list[Action],
    start_mm: Position,
    end_mm: Position,
    unit: Position,
    length_mm: float = 0.0,
    nominal_mm_s: float = 0.0,
    accel_mm_s2: float = 0.0,
) -> Block:
    """A block with its geometry and limits but no speeds or times yet."""
    zero = 0.0
    return Block(move, actions, start_mm, end_mm, unit, length_mm, nominal_mm_s, accel_mm_s2,
                 zero, zero, zero, zero, zero, zero, zero, zero)  # fmt: skip
