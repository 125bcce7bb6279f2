"""The kernel's event bus and machine state.

Events are delivered synchronously, in subscription order, so that ``halt`` turns every tool
off before :meth:`EventBus.emit` returns. A subscriber that raises is logged and skipped: one
faulty listener must never stop the others from hearing a halt.

Kernel events (arguments in brackets):
  ``halt`` (reason: str) · ``clear_halt`` · ``reset`` (Ctrl-X) · ``stop`` (reason: str) ·
  ``hold`` · ``resume`` · ``motors_enable`` ·
  ``motors_disable`` · ``second`` (now_s) · ``state`` (MachineState) · ``action`` (Action) ·
  ``program_end`` · ``push`` (message line for every connection) · ``shutdown`` ·
  ``override`` (feed %, rapid %, spindle %)
"""

from __future__ import annotations

import enum
import logging
from collections import defaultdict
from collections.abc import Callable
from typing import Any

log = logging.getLogger("motiond.events")


class MachineState(enum.Enum):
    """Grbl's machine states, as shown in status reports."""

    IDLE = "Idle"
    RUN = "Run"
    HOLD = "Hold"
    JOG = "Jog"
    HOME = "Home"
    ALARM = "Alarm"
    CHECK = "Check"
    DOOR = "Door"
    SLEEP = "Sleep"


class Event(enum.StrEnum):
    """Every event on the bus, with the arguments its subscribers get."""

    STATE = "state"  # (MachineState) the state changed
    HALT = "halt"  # (reason: str) motion stopped at once, tools off: ALARM, M112, job abort
    CLEAR_HALT = "clear_halt"  # () $X / M999 unlocked
    HOLD = "hold"  # () a feed hold began
    HOLD_STOPPED = "hold_stopped"  # () the hold's deceleration ended
    RESUME = "resume"  # () cycle start after a hold
    RESET = "reset"  # () soft reset (Ctrl-X)
    STOP = "stop"  # (reason: str) a stop: what was requested before it is dropped (state.py)
    SHUTDOWN = "shutdown"  # () the server is stopping: tools off
    ACTION = "action"  # (Action) motion reached an ordered action
    OVERRIDE = "override"  # (feed, rapid, spindle: percent)
    SPINDLE_STOP = "spindle_stop"  # () Grbl's spindle stop override during a hold
    TOGGLE_COOLANT = "toggle_coolant"  # ("flood" | "mist") Grbl's realtime coolant toggles
    MOTORS_ENABLE = "motors_enable"  # () M17
    MOTORS_DISABLE = "motors_disable"  # () M18/M84, $SLP
    PROGRAM_END = "program_end"  # () M2/M30 reached
    SECOND = "second"  # (now_s) once a second of the kernel's clock
    PUSH = "push"  # (message) an unsolicited line for every connection
    JOB = "job"  # (JobProgress | None) a job started, paused, resumed or ended


class EventBus:
    """Named synchronous events with any number of subscribers; a name outside
    :class:`Event` is refused (ValueError), so a misspelt subscription fails at start-up."""

    def __init__(self) -> None:
        self._subscribers: defaultdict[str, list[Callable[..., None]]] = defaultdict(list)
        self.failures: list[tuple[str, BaseException]] = []

    def subscribe(self, event: str, callback: Callable[..., None]) -> Callable[[], None]:
        """Subscribe; returns a function that unsubscribes."""
        event = Event(event)
        self._subscribers[event].append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers[event]:
                self._subscribers[event].remove(callback)

        return unsubscribe

    def emit(self, event: str, *args: Any) -> None:
        """Call every subscriber of ``event``; failures are logged and recorded, never raised."""
        event = Event(event)
        for callback in tuple(self._subscribers.get(event, ())):
            try:
                callback(*args)
            except Exception as exc:  # noqa: BLE001 - one listener must not silence the others
                log.exception("subscriber %r of event %r failed", callback, event)
                self.failures.append((event, exc))
