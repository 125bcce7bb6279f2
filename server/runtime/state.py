"""The machine state, its alarm and its stops, with one owner: :class:`MachineStatus`.

The kernel, the motion pipeline and the modules all read and change the state through this
object; every change is an event on the bus (``state``, ``halt``, ``clear_halt``, ``push``,
``stop``), so transports and modules follow it without knowing who changed it. Raising an
alarm stops motion first (the ``stop_motion`` hook, the pipeline's), then tells everyone why.

**The one stop mechanism.** Every stop (Ctrl-X, M112 in any dialect, an alarm, Klipper's
``emergency_stop``, ``machine.reset``, M410, a job's abort) goes through
:meth:`MachineStatus.stop`, which counts it in :attr:`MachineStatus.stops` (the stop
generation) and emits ``stop``. Whatever is requested carries the generation it was requested
in (:meth:`MachineStatus.ticket`), and
whoever is about to start it checks the ticket (:meth:`MachineStatus.still_valid`): a request
made before a stop never starts after it, wherever it waited (a connection's queue, the
dispatcher's turn, a job's fit check, a deferred jog). Queues that hold requests also listen
to ``stop`` to drop them at once (and free their memory).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from server.runtime.events import Event, EventBus, MachineState

log = logging.getLogger("motiond.state")


class MachineStatus:
    """Owns the machine state and the current alarm.

    Attributes:
        state: the Grbl state (Idle, Run, Hold, Alarm...).
        alarm_code, alarm_message: the alarm in force (0 and "" when there is none).
        stop_motion: called first by :meth:`alarm` (the motion pipeline sets it).
        before_unlock: called by :meth:`clear_alarm` before the state returns to Idle.
    """

    def __init__(self, events: EventBus) -> None:
        self.events = events
        self.state = MachineState.IDLE
        self.alarm_code = 0
        self.alarm_message = ""
        self.stops = 0  # the stop generation: how many stops there have been
        self.stop_motion: Callable[[], None] = lambda: None
        self.before_unlock: Callable[[], None] = lambda: None

    # -- the stop generation ----------------------------------------------------------------
    def ticket(self) -> int:
        """The stop generation a request made now belongs to (see the module docstring)."""
        return self.stops

    def still_valid(self, ticket: int) -> bool:
        """Whether a request made with ``ticket`` may still start: no stop came since."""
        return ticket == self.stops

    def stop(self, reason: str) -> None:
        """A stop: everything requested before it is void (``stop`` event: queues drop it)."""
        self.stops += 1
        log.info("stop %d: %s", self.stops, reason)
        self.events.emit(Event.STOP, reason)

    def set_state(self, state: MachineState) -> None:
        if state is not self.state:
            self.state = state
            self.events.emit(Event.STATE, state)

    def push(self, message: str) -> None:
        """Send an unsolicited line (``ALARM:2``, ``[MSG:...]``) to every connection."""
        self.events.emit(Event.PUSH, message)

    def alarm(self, code: int, message: str, *, explain: bool = True) -> None:
        """Stop motion and tools at once, lock G-code out, tell everyone why (``explain``
        False: the caller pushes the ``[MSG:]`` itself, after the banner of a reset)."""
        log.error("ALARM:%d %s", code, message)
        self.alarm_code, self.alarm_message = code, message
        self.stop_motion()
        self.stop(f"ALARM:{code}")
        self.set_state(MachineState.ALARM)
        self.events.emit(Event.HALT, message)
        self.push(f"ALARM:{code}")
        if explain:
            self.push(f"[MSG:{message}]")

    def clear_alarm(self) -> None:
        """``$X`` / ``M999``: unlock after an alarm."""
        if self.state is MachineState.ALARM:
            self.alarm_code, self.alarm_message = 0, ""
            self.before_unlock()
            self.set_state(MachineState.IDLE)
            self.events.emit(Event.CLEAR_HALT)
            self.push("[MSG:Caution: Unlocked]")
