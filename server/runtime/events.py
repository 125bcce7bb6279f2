"""The kernel's event bus and machine state.

Events are delivered synchronously, in subscription order, so that ``halt`` turns every tool
off before :meth:`EventBus.emit` returns. A subscriber that raises is logged and skipped: one
faulty listener must never stop the others from hearing a halt.

Kernel events (arguments in brackets):
  ``halt`` (reason: str) · ``clear_halt`` · ``reset`` (Ctrl-X) ·
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


class EventBus:
    """Named synchronous events with any number of subscribers."""

    def __init__(self) -> None:
        self._subscribers: defaultdict[str, list[Callable[..., None]]] = defaultdict(list)
        self.failures: list[tuple[str, BaseException]] = []

    def subscribe(self, event: str, callback: Callable[..., None]) -> Callable[[], None]:
        """Subscribe; returns a function that unsubscribes."""
        self._subscribers[event].append(callback)

        def unsubscribe() -> None:
            if callback in self._subscribers[event]:
                self._subscribers[event].remove(callback)

        return unsubscribe

    def emit(self, event: str, *args: Any) -> None:
        """Call every subscriber of ``event``; failures are logged and recorded, never raised."""
        for callback in tuple(self._subscribers.get(event, ())):
            try:
                callback(*args)
            except Exception as exc:  # noqa: BLE001 - one listener must not silence the others
                log.exception("subscriber %r of event %r failed", callback, event)
                self.failures.append((event, exc))
