"""What the step generator publishes and whom it tells: the motion's state at every tick
(sampled by status, modules and the job's clock), the feed hold's states, and the listener its
owner gives it. Pure data, apart from :mod:`server.motion.stepgen` so the readers of the state
need not import the generator."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol

from server.motion.moves import Action, MoveKind, Position, ToolMode


class HoldState(enum.Enum):
    NONE = "none"
    DECELERATING = "decelerating"  # Grbl's Hold:1
    STOPPED = "stopped"  # Grbl's Hold:0


@dataclass(slots=True)
class MotionState:
    """What the step generator publishes at every tick (sampled by modules and status).

    Units: mm, mm/s, seconds on the kernel's clock.
    """

    time_s: float = 0.0
    position_mm: Position = ()
    speed_mm_s: float = 0.0
    nominal_mm_s: float = 0.0
    kind: MoveKind | None = None
    tool_mode: ToolMode = ToolMode.OFF
    s_value: float = 0.0
    line_number: int | None = None
    queue_depth: int = 0
    moving: bool = False
    hold: HoldState = HoldState.NONE
    blocks_done: int = 0
    motion_time_s: float = 0.0  # planned time of all completed blocks and the current one so far


class MotionListener(Protocol):
    """What the step generator tells its owner."""

    def on_action(self, action: Action) -> None:
        """Motion reached an ordered action."""

    def on_idle(self) -> None:
        """The queue ran empty and motion stopped."""

    def on_hold_stopped(self) -> None:
        """A feed hold (or jog cancel) came to a stop."""
