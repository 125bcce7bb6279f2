"""The machine's realtime commands: hold, resume, jog cancel, reset, stop, overrides, at once.

:class:`RealtimeCommands` is the part of :class:`~server.machine.machine.Machine` (a base class
of it) that acts without waiting for the line queue: feed hold and cycle start, jog cancel,
soft reset, M112 and the M410 quickstop, the coolant and spindle-stop toggles, the
feed/rapid/spindle overrides, and the halts that resynchronise the pipeline to where the steps
are. Every entry point reaches it
through :class:`~server.kernel.control.MachineControl`. Its state is the machine's, created by
``Machine.__init__``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from server.errors import Alarm
from server.motion.motion_state import HoldState
from server.motion.moves import Position, ToolMode
from server.protocol.events import Realtime
from server.protocol.reports import UNLOCK_HINT
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    import asyncio

    from server.gcode.interpreter import Interpreter
    from server.machine.machine import ToolState
    from server.motion.backend import Backend
    from server.motion.planner import Planner
    from server.motion.stepgen import StepGenerator
    from server.runtime.events import EventBus
    from server.runtime.state import MachineStatus


class RealtimeCommands:
    """Realtime commands and halts; see the module docstring."""

    # The machine's state this part reads and writes (set by Machine.__init__).
    events: EventBus
    status: MachineStatus
    backend: Backend
    interpreter: Interpreter
    planner: Planner
    stepgen: StepGenerator
    room: asyncio.Event
    idle_event: asyncio.Event
    epoch: int
    tool: ToolState
    feed_override: int
    rapid_override: int
    spindle_override: int
    _cancelling_jog: bool

    if TYPE_CHECKING:
        def leave_check_mode(self) -> None: ...  # the machine's modes

    def spindle_stop(self) -> None:
        """Grbl's spindle stop override (0x9E): the spindle module toggles during a hold."""
        self.events.emit(Event.SPINDLE_STOP)

    def realtime(self, command: Realtime) -> None:
        """Act on a realtime byte at once (status and reset are the session's)."""
        action = _REALTIME_ACTIONS.get(command)
        if action is not None:
            action(self)
            return
        feed, rapid, spindle = _OVERRIDE_STEPS.get(command, (None, None, None))
        self.set_overrides(
            feed=None if feed is None else (100 if feed == 0 else self.feed_override + feed),
            rapid=rapid,
            spindle=None
            if spindle is None
            else (100 if spindle == 0 else self.spindle_override + spindle),
        )

    def step_overrides(self, commands: list[Realtime]) -> None:
        """Several override bytes in a row (0x90-0x9D): one change, each step clamped as it
        would have been alone; nothing when they leave the overrides as they are."""
        feed, rapid, spindle = self.feed_override, self.rapid_override, self.spindle_override
        for command in commands:
            feed_step, rapid_value, spindle_step = _OVERRIDE_STEPS[command]
            if feed_step is not None:
                feed = 100 if feed_step == 0 else max(10, min(200, feed + feed_step))
            if rapid_value is not None:
                rapid = rapid_value
            if spindle_step is not None:
                spindle = 100 if spindle_step == 0 else max(10, min(200, spindle + spindle_step))
        self.set_overrides(feed, rapid, spindle)

    def toggle_coolant(self, which: str) -> None:
        """Realtime flood/mist toggle (0xA0/0xA1): at once, reflected in status ``A:``."""
        if which == "flood":
            self.tool.flood = not self.tool.flood
        else:
            self.tool.mist = not self.tool.mist
        self.events.emit(Event.TOGGLE_COOLANT, which)

    def emergency_stop(self) -> None:
        """M112: halt at once, before the lines queued ahead of it run."""
        if self.status.state is not MachineState.ALARM:
            self.status.alarm(Alarm.HALT, "emergency stop (M112): $X or M999 to unlock")

    def quickstop(self, reason: str = "quickstop (M410)") -> None:
        """M410 and a job's abort: stop at once, flush the queue, tools off; no alarm.

        The position stays where the steps are; the modal spindle/laser and coolant are off,
        so the next move does not switch them on again."""
        self.stop_now()
        self.interpreter.tools_off()
        self.tool.mode, self.tool.s, self.tool.flood, self.tool.mist = (
            ToolMode.OFF, 0.0, False, False)
        self.events.emit(Event.HALT, reason)
        if self.status.state in (MachineState.RUN, MachineState.HOLD, MachineState.JOG):
            self.status.set_state(MachineState.IDLE)

    def feed_hold(self) -> None:
        if self.status.state is MachineState.HOME:  # as in Grbl: homing ignores feed hold
            return
        if self.status.state is MachineState.HOLD and self.stepgen.state.hold is not HoldState.NONE:
            return  # already holding: a repeated '!' changes nothing
        if self.stepgen.idle and self.status.state is MachineState.IDLE:
            self.stepgen.hold()  # Hold:0 at once, as Grbl: queued motion waits for '~'
            self.status.set_state(MachineState.HOLD)
            self.events.emit(Event.HOLD)  # a focusing `fire` stops too
            return
        if self.status.state in (MachineState.RUN, MachineState.JOG) or not self.stepgen.idle:
            if self.status.state is MachineState.JOG:
                self.cancel_jog()
                return
            self.stepgen.hold()
            self.status.set_state(MachineState.HOLD)
            self.events.emit(Event.HOLD)

    def cycle_start(self) -> None:
        if self.status.state is MachineState.HOLD:
            self.stepgen.resume()
            self.status.set_state(MachineState.IDLE if self.stepgen.idle else MachineState.RUN)
            self.events.emit(Event.RESUME)

    def cancel_jog(self) -> None:
        """Jog cancel: decelerate to a stop, then drop the remaining jog moves."""
        if self.status.state is not MachineState.JOG:
            return
        self._cancelling_jog = True
        self.stepgen.hold()
        if self.stepgen.state.hold is not HoldState.DECELERATING:
            self._finish_jog_cancel()

    def _finish_jog_cancel(self) -> None:
        self._cancelling_jog = False
        self.stop_now()
        self.status.set_state(MachineState.IDLE)

    def soft_reset(self) -> None:
        """Ctrl-X: stop at once, flush, keep the position; ALARM:3 if motion was interrupted
        (not after a hold that had stopped, as Grbl), ALARM:6 alone during homing; overrides
        back to 100 %. After an alarm, as Grbl: the alarm, the banner (each connection's
        reset), then ``[MSG:'$H'|'$X' to unlock]``, then motiond's own reason."""
        state = self.stepgen.state
        moving = state.moving and state.hold is not HoldState.STOPPED
        homing = self.status.state is MachineState.HOME
        why = ""
        if homing:
            why = "homing fail: reset during the homing cycle"
            self.status.alarm(Alarm.HOMING_RESET, why, explain=False)  # (halts motion first)
        elif moving:
            why = "reset while in motion: position may be lost, re-home"
            self.status.alarm(Alarm.ABORT_CYCLE, why, explain=False)
        else:  # (halted once only: a second halt is a second Ctrl-X to a Grbl board)
            self._halt_motion()
        self.set_overrides(100, 100, 100)
        self.leave_check_mode()
        self.interpreter.reset()
        if not why:
            self.status.stop("reset (Ctrl-X)")
            if self.status.state is not MachineState.ALARM:
                self.status.set_state(MachineState.IDLE)
        self.events.emit(Event.RESET)
        if why:
            self.status.push(UNLOCK_HINT)
            self.status.push(f"[MSG:{why}]")

    def _halt_motion(self) -> None:
        """Alarm, M112, Ctrl-X: the hardware drops what it has queued, then :meth:`stop_now`;
        the spindle, laser and coolant are off (and reported so)."""
        self.backend.halt()
        self.stop_now()
        self.interpreter.tools_off()  # M5 S0 M9 in the modal state too, as a reset board
        tool = self.tool
        tool.mode, tool.s, tool.flood, tool.mist = ToolMode.OFF, 0.0, False, False

    def stop_now(self) -> None:
        """Halt motion at once and resynchronise everything to where the steps are."""
        self.epoch += 1
        self.stepgen.stop_now()
        position = self.stepgen.state.position_mm
        self.interpreter.set_position(position)
        self.room.set()
        self.idle_event.set()

    def set_machine_position(self, position_mm: Position) -> None:
        """Redefine where the machine is without moving it (homing sets the axes' ends)."""
        self.stop_now()
        self.stepgen.rebase(position_mm)
        self.planner.set_position(position_mm)
        self.interpreter.set_position(position_mm)

    def set_overrides(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        before = (self.feed_override, self.rapid_override, self.spindle_override)
        if feed is not None:
            self.feed_override = max(10, min(200, feed))
        if rapid is not None:
            self.rapid_override = rapid
        if spindle is not None:
            self.spindle_override = max(10, min(200, spindle))
        if (self.feed_override, self.rapid_override, self.spindle_override) == before:
            return  # an override at its limit, or repeated: nothing to re-plan or report
        self.planner.set_overrides(self.feed_override / 100, self.rapid_override / 100)
        self.events.emit(
            "override", self.feed_override, self.rapid_override, self.spindle_override
        )


_REALTIME_ACTIONS: dict[Realtime, Callable[[RealtimeCommands], None]] = {
    Realtime.HOLD: RealtimeCommands.feed_hold,
    Realtime.DOOR: RealtimeCommands.feed_hold,
    Realtime.RESUME: RealtimeCommands.cycle_start,
    Realtime.JOG_CANCEL: RealtimeCommands.cancel_jog,
    Realtime.SPINDLE_STOP: RealtimeCommands.spindle_stop,
    Realtime.FLOOD: lambda m: m.toggle_coolant("flood"),
    Realtime.MIST: lambda m: m.toggle_coolant("mist"),
}
# (feed step, rapid value, spindle step); a step of 0 means "back to 100%".
_OVERRIDE_STEPS: dict[Realtime, tuple[int | None, int | None, int | None]] = {
    Realtime.FEED_100: (0, None, None),
    Realtime.FEED_PLUS_10: (10, None, None),
    Realtime.FEED_MINUS_10: (-10, None, None),
    Realtime.FEED_PLUS_1: (1, None, None),
    Realtime.FEED_MINUS_1: (-1, None, None),
    Realtime.RAPID_100: (None, 100, None),
    Realtime.RAPID_50: (None, 50, None),
    Realtime.RAPID_25: (None, 25, None),
    Realtime.SPINDLE_100: (None, None, 0),
    Realtime.SPINDLE_PLUS_10: (None, None, 10),
    Realtime.SPINDLE_MINUS_10: (None, None, -10),
    Realtime.SPINDLE_PLUS_1: (None, None, 1),
    Realtime.SPINDLE_MINUS_1: (None, None, -1),
}
