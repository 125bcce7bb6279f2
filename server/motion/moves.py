"""The data that crosses the interpreter -> planner -> step generator boundaries.

Units are always machine millimetres, mm/s and seconds, and positions are absolute machine
coordinates with one value per configured axis, in the configuration's axis order.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

Position = tuple[float, ...]


class MoveKind(enum.Enum):
    """What a move is for; the laser never fires on RAPID, JOG or HOMING moves."""

    RAPID = "rapid"
    FEED = "feed"
    ARC = "arc"  # one chord of a G2/G3 arc
    PROBE = "probe"
    JOG = "jog"
    HOMING = "homing"


class ToolMode(enum.IntEnum):
    """The spindle/laser modal state: M3, M4 or M5."""

    CW = 3  # M3: constant power (laser) or clockwise spindle
    CCW = 4  # M4: dynamic power (laser) or counter-clockwise spindle
    OFF = 5  # M5


class ActionName(enum.StrEnum):
    """The ordered actions the interpreter produces; modules add names of their own."""

    SPINDLE = "spindle"  # mode: ToolMode, s
    COOLANT = "coolant"  # mist, flood: bool
    DWELL = "dwell"  # seconds (lead_s); reason
    PAUSE = "pause"  # optional: bool (M0/M1)
    PROGRAM_END = "program_end"  # code (M2/M30)
    TOOL_CHANGE = "tool_change"  # tool
    MOTORS = "motors"  # enabled: bool


@dataclass(slots=True)
class Action:
    """A non-motion command executed in order with motion (DESIGN.md rule 3).

    A *follow* action (``lead_s == 0``: tool on/off, S change, coolant, output pin) takes effect
    when motion reaches it and does not stop motion. A *lead* action (``lead_s > 0`` or
    ``stops_motion``: dwell, pause, program end) makes motion come to a stop first; dwell then
    waits ``lead_s`` seconds.

    ``name`` is an :class:`ActionName` (a StrEnum, so it equals its string) or a module's own
    name (``switch``, ``laser``).
    """

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    lead_s: float = 0.0
    stops_motion: bool = False


@dataclass(slots=True)
class Move:
    """A straight move to ``target_mm`` (absolute machine coordinates, one value per axis).

    ``feed_mm_s`` is the requested speed along the path; the planner lowers it to the axes'
    limits. ``tool_mode`` and ``s_value`` are the modal M3/M4/M5 and S in force for this move, so
    that laser power changes between segments ride inside the blocks without stopping motion.
    ``actions`` run when motion reaches the start of this move.
    """

    target_mm: Position
    feed_mm_s: float
    kind: MoveKind
    tool_mode: ToolMode = ToolMode.OFF
    s_value: float = 0.0
    line_number: int | None = None
    actions: list[Action] = field(default_factory=list)


class SyncKind(enum.StrEnum):
    """What a :class:`Sync` asks of the machine."""

    REPORT_POSITION = "report_position"  # M114: answer with the current position
    HALT = "halt"  # M112
    CLEAR_HALT = "clear_halt"  # M999
    PROBE = "probe"  # G38.x: wait for the probe move, resynchronise, report
    HOME = "home"  # G28.2: run the homing cycle (a module's sync handler)
    MESSAGE = "message"  # report params["lines"] before ok (a module code's answer)
    WAIT = "wait"  # M400: answer once every queued move has been executed
    QUICKSTOP = "quickstop"  # M410: stop at once, flush the queue, tools off (no alarm)


@dataclass(slots=True)
class Sync:
    """A request the interpreter cannot fulfil alone; the machine carries it out in order.

    Params by kind: ``probe``: ``towards``, ``error_on_fail`` (bool); ``home``: ``axes``
    (axis indices; empty: all); ``message``: ``lines``. A plain string equal to a kind's value
    is accepted and turned into the :class:`SyncKind`.
    """

    kind: SyncKind
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.kind = SyncKind(self.kind)


Output = Move | Action | Sync
