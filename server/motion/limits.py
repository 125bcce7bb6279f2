"""The planner's settings, its column layout, and the per-block limits derived in batches.

Pure numpy (no asyncio, no I/O). Each block is one column of a :class:`BlockColumns` array; its
rows are the numbers given at append time, the limits :class:`Limits` derives from them when
staged blocks are synced (the axes' acceleration and rate projected on the block's direction,
the nominal speed under the overrides, the junction limit with the block before and the cap on
v² at its entry node), and the trapezoid the planner writes. Units: mm, mm/s, mm/s², s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from server.motion.block import BlockColumns, FloatArray
from server.motion.moves import Move, MoveKind
from server.motion.trapezoid import PROFILE_ROWS, axis_limits, junction_speeds_sq, node_caps

# Rows of the per-block column array. Given at append time: ...
LENGTH, FEED, KIND, LEAD = range(4)
# ... derived in batches when staged blocks are synced: ...
ACCEL, RATE, NOMINAL, JUNCTION = range(4, 8)
# ... written by plan(): ...
ENTRY, CRUISE, EXIT, RAMP1, FLAT, RAMP2, DURATION = range(8, 8 + PROFILE_ROWS)
# ... the cap on v² at the block's entry node (derived), its time estimate (given at append),
# and the direction, one row per axis, from UNIT on.
CAP, ESTIMATE = DURATION + 1, DURATION + 2
UNIT = ESTIMATE + 1

# KIND codes: which override scales a block's nominal speed.
NO_OVERRIDE, FEED_OVERRIDE, RAPID_OVERRIDE = 0.0, 1.0, 2.0
CUTTING_CODE = FEED_OVERRIDE
"""The KIND of exactly the FEED, ARC and PROBE moves (jog and homing have no override)."""
FEED_OVERRIDE_RANGE = (0.1, 2.0)
RAPID_OVERRIDE_RANGE = (0.25, 1.0)
_RAPID, _JOG, _HOMING = MoveKind.RAPID, MoveKind.JOG, MoveKind.HOMING


@dataclass(frozen=True, slots=True)
class PlannerSettings:
    """Machine limits the planner needs; per-axis tuples follow the configuration's axis order.

    ``max_rate_mm_s`` and ``accel_mm_s2`` are per axis; ``junction_deviation_mm`` is δ of the
    junction model; the window is full at ``max_blocks`` blocks or ``max_planned_s`` seconds of
    planned motion; nominal speeds never drop below ``min_feed_mm_s``. The real-time budget of
    a call (the plan is the same whatever they are): one ``plan()`` plans at most
    ``plan_blocks`` blocks, and staged blocks are synced (copied into the columns, their
    limits derived) ``sync_blocks`` at a time, so no append or plan does that for a window;
    offline runs, with no loop to keep, sync more at once (fewer, larger numpy calls).
    """

    max_rate_mm_s: tuple[float, ...]
    accel_mm_s2: tuple[float, ...]
    junction_deviation_mm: float = 0.01
    max_blocks: int = 4096
    max_planned_s: float = 0.5
    min_feed_mm_s: float = 0.01
    plan_blocks: int = 512
    sync_blocks: int = 128

    def __post_init__(self) -> None:
        if len(self.max_rate_mm_s) != len(self.accel_mm_s2) or not self.max_rate_mm_s:
            raise ValueError("max_rate_mm_s and accel_mm_s2 need one value per axis")
        if min(self.max_rate_mm_s) <= 0 or min(self.accel_mm_s2) <= 0:
            raise ValueError("axis rates and accelerations must be positive")
        if self.junction_deviation_mm <= 0 or self.min_feed_mm_s <= 0:
            raise ValueError("junction_deviation_mm and min_feed_mm_s must be positive")
        if self.plan_blocks < 1 or self.sync_blocks < 1:
            raise ValueError("plan_blocks and sync_blocks must be at least 1")


class Limits:
    """Derives the limit rows of a window's columns from the machine's limits and overrides.

    ``accel_mm_s2`` and ``max_rate_mm_s`` are per axis; ``feed_override`` and
    ``rapid_override`` scale the nominal speeds of feed moves and rapids.
    """

    def __init__(self, columns: BlockColumns, accel_mm_s2: tuple[float, ...],
                 max_rate_mm_s: tuple[float, ...], junction_deviation_mm: float,
                 min_feed_mm_s: float) -> None:
        self._columns = columns
        self._units = slice(UNIT, UNIT + len(accel_mm_s2))
        # accelerations then rates, as the ACCEL and RATE rows
        self._inverse_limits = (1.0 / np.array([accel_mm_s2, max_rate_mm_s]))[:, :, None]
        self.junction_deviation_mm = junction_deviation_mm
        self.min_feed_mm_s = min_feed_mm_s
        self.feed_override = self.rapid_override = 1.0

    def derive(self, first: int, stop: int) -> None:
        """Axis limits, nominal speeds and junction limits of columns ``first .. stop-1``."""
        data, new = self._columns.data, slice(first, stop)
        data[ACCEL : RATE + 1, new] = axis_limits(data[self._units, new], self._inverse_limits)
        self.nominals(data[FEED, new], data[RATE, new], data[KIND, new], out=data[NOMINAL, new])
        self.derive_junctions(first, stop)

    def derive_junctions(self, first: int, stop: int) -> None:
        """Junction limits of columns ``first .. stop-1`` against the column before each.

        The head's own junction never counts (its entry is the start speed).
        """
        data, begin = self._columns.data, max(first, self._columns.head + 1)
        data[JUNCTION, first:begin] = 0.0
        if begin >= stop:
            return
        before, after = slice(begin - 1, stop - 1), slice(begin, stop)
        accel = np.minimum(data[ACCEL, before], data[ACCEL, after])
        units = self._units
        limit = junction_speeds_sq(data[units, before], data[units, after], accel,
                                   self.junction_deviation_mm)
        limit[data[LENGTH, before] * data[LENGTH, after] == 0.0] = 0.0  # next to a still block
        data[JUNCTION, after] = limit

    def derive_caps(self, first: int, stop: int) -> None:
        """The cap ``L`` on v² at the entry node of columns ``first .. stop-1``: their junction
        limits and both neighbours' nominal speeds; infinite at the head (its speed is the
        start speed)."""
        columns = self._columns
        data, begin = columns.data, max(first, columns.head + 1)
        data[CAP, first:begin] = np.inf
        if begin < stop:
            caps = node_caps(data[NOMINAL, begin - 1 : stop], data[JUNCTION, begin:stop])
            data[CAP, begin:stop] = caps[:-1]

    def renominate(self) -> None:
        """Recompute the window's nominal speeds and caps (the overrides changed)."""
        columns = self._columns
        window = columns.window()
        window[NOMINAL] = self.nominals(window[FEED], window[RATE], window[KIND])
        self.derive_caps(columns.head, columns.tail)

    def nominals(
        self, feed: FloatArray, rate: FloatArray, kind: FloatArray, out: FloatArray | None = None
    ) -> FloatArray:
        """Nominal speeds (mm/s): the feed scaled by its override, capped by the axis rate
        limit (scaled by the rapid override for rapids), never under ``min_feed_mm_s``."""
        if self.feed_override != 1.0:
            feed = feed * np.where(kind == FEED_OVERRIDE, self.feed_override, 1.0)
        if self.rapid_override != 1.0:
            rate = rate * np.where(kind == RAPID_OVERRIDE, self.rapid_override, 1.0)
        nominal = np.minimum(feed, rate, out=out)
        return np.maximum(nominal, self.min_feed_mm_s, out=nominal)

    def of_direction(self, unit: tuple[float, ...], move: Move) -> tuple[float, float]:
        """The acceleration and nominal speed of one move along ``unit`` (a block built by
        hand, such as a feed hold's remainder)."""
        accel, rate = axis_limits(np.array(unit)[:, None], self._inverse_limits)
        kind, feed = kind_and_feed(move)
        nominal = self.nominals(np.array([feed]), rate, np.array([kind]))
        return float(accel.item()), float(nominal.item())


def kind_and_feed(move: Move) -> tuple[float, float]:
    """The override code of a move and its requested feed (mm/s; inf for rapids)."""
    if move.kind is _RAPID:
        return RAPID_OVERRIDE, math.inf
    feed = move.feed_mm_s if move.feed_mm_s > 0.0 else 0.0
    return (NO_OVERRIDE if move.kind in (_JOG, _HOMING) else FEED_OVERRIDE), feed
