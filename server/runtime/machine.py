"""The motion pipeline: interpreter -> planner -> step generator -> backend, owned by the kernel.

:class:`Machine` is the default G-code handler of the dispatcher. It runs the interpreter, feeds
moves and ordered actions to the planner (waiting while it is full: that wait is the flow
control that delays a sender's ``ok``), carries out the interpreter's sync requests, and applies
realtime commands (hold, resume, reset, jog cancel, overrides) at once.
"""

from __future__ import annotations

import asyncio
import copy
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from typing import Any

from server.config import Config
from server.errors import Alarm, CommandError, Error, SoftLimitError
from server.gcode.codes import CodeTable
from server.gcode.interpreter import Interpreter
from server.motion.feed import offer
from server.motion.moves import (
    Action,
    ActionName,
    Move,
    MoveKind,
    Output,
    Position,
    Sync,
    SyncKind,
    ToolMode,
)
from server.motion.planner import Planner
from server.motion.stepgen import HoldState, StepGenerator
from server.protocol.events import Realtime
from server.protocol.reports import StatusSnapshot
from server.runtime.clock import Clock
from server.runtime.dispatcher import Command, Dispatcher
from server.runtime.events import Event, EventBus, MachineState
from server.runtime.parts import (
    build_backend,
    interpreter_settings,
    planner_settings,
    settings_path,
)
from server.runtime.settings import Settings
from server.runtime.state import MachineStatus

log = logging.getLogger("motiond.machine")


@dataclass(slots=True)
class ToolState:
    """The spindle/laser and coolant state as motion last reached it."""

    mode: ToolMode = ToolMode.OFF
    s: float = 0.0
    flood: bool = False
    mist: bool = False


SyncHandler = Callable[[dict[str, Any]], Awaitable[list[str]]]


class Machine:
    """Owns the motion pipeline; see the module docstring."""

    def __init__(
        self, config: Config, clock: Clock, events: EventBus, status: MachineStatus
    ) -> None:
        core = config.core
        self.clock, self.events, self.status = clock, events, status
        status.stop_motion, status.before_unlock = self._halt_motion, self.leave_check_mode
        self.core = core
        self.backend = build_backend(core)
        self.codes = CodeTable()
        self.spin_up_delay_s = 0.0
        self.sync_handlers: dict[SyncKind, SyncHandler] = {}
        self.interpreter = Interpreter(interpreter_settings(core), self.codes)
        origin = tuple(0.0 for _ in core.axis_names)
        self.interpreter.set_position(origin)
        self.planner = Planner(planner_settings(core), origin)
        self.stepgen = StepGenerator(
            self.planner,
            self.backend,
            tuple(a.steps_per_mm for a in core.axes.values()),
            self,
            tick_hz=core.stepgen.tick_hz,
        )
        self.room = asyncio.Event()
        self.idle_event = asyncio.Event()
        self.idle_event.set()
        self.check_mode = False
        self.epoch = 0  # incremented by every halt/reset; lines waiting across one are dropped
        self.tool = ToolState()
        self._cancelling_jog = False
        self._check_saved: Interpreter | None = None
        self._defaults = core.model_copy(deep=True)
        self.feed_override = 100
        self.rapid_override = 100
        self.spindle_override = 100
        self.settings = Settings(  # last: it applies saved values
            core, settings_path(config),
            is_idle=lambda: self.stepgen.idle, apply=self.apply_settings,
        )

    # -- the G-code handler -----------------------------------------------------------------
    async def handle_gcode(self, command: Command) -> list[str]:
        outputs = self.interpret(command)
        self._arm_probe(outputs)
        return await self._feed(outputs)

    def interpret(self, command: Command) -> list[Output]:
        """The line's outputs from the interpreter; a target outside the travel alarms."""
        assert command.line is not None
        try:
            return self.interpreter.execute(command.line)
        except SoftLimitError as exc:
            self.status.alarm(Alarm.SOFT_LIMIT, f"soft limit: {exc.message}")
            raise

    async def _feed(self, outputs: list[Output]) -> list[str]:
        """Offer the line's outputs to the planner (:func:`~server.motion.feed.offer`, as
        ``estimate`` does), waiting for room and carrying out sync requests in order."""
        messages: list[str] = []
        index, epoch = 0, self.epoch
        while index < len(outputs):
            if self.check_mode:  # interpreted, never planned
                while index < len(outputs) and type(outputs[index]) is not Sync:
                    index += 1
            else:
                taken = offer(self.planner, outputs, index)
                if taken > index:
                    self._note_input(MachineState.RUN)
                index = taken
            if index == len(outputs):
                break
            output = outputs[index]
            if type(output) is Sync:
                messages += await self.sync(output)
                index += 1
            else:
                await self._wait_for_room(epoch)
        return messages

    def _arm_probe(self, outputs: list[Output]) -> None:
        for output in outputs:
            if type(output) is Sync and output.kind is SyncKind.PROBE:
                self.stepgen.probe_towards = bool(output.params.get("towards", True))
                self.stepgen.probe_hit = False

    async def queue_move(self, move: Move) -> None:
        """Append a move, waiting while the planner is full."""
        if self.check_mode:
            return
        await self._wait_for_room()
        self.planner.append(move)
        self._note_input(MachineState.JOG if move.kind is MoveKind.JOG else MachineState.RUN)

    async def queue_action(self, action: Action) -> None:
        """Append an ordered action, waiting while the planner is full."""
        if self.check_mode:
            return
        await self._wait_for_room()
        self.planner.append_action(action)
        self._note_input(MachineState.RUN)

    async def _wait_for_room(self, epoch: int | None = None) -> None:
        """Wait while the planner is full; refuse the line if motion was reset meanwhile
        (``epoch``: the machine's epoch when the line began; default now)."""
        epoch = self.epoch if epoch is None else epoch
        while self.planner.is_full():
            self.room.clear()
            await self.room.wait()
        if epoch != self.epoch:
            raise CommandError(
                Error.BUSY, "motion was reset while this line waited; it was not run"
            )

    def _note_input(self, state: MachineState) -> None:
        self.idle_event.clear()
        self.stepgen.note_input(self.clock.now_s())
        if self.status.state is MachineState.IDLE:
            self.status.set_state(state)

    @property
    def busy(self) -> bool:
        """Motion is queued or running (its source owns the machine until it ends)."""
        return not self.stepgen.idle

    def register_commands(self, dispatcher: Dispatcher) -> None:
        """Commands this machine adds to the core's (a downstream controller's); none here."""

    def status_snapshot(self, rx_free_bytes: int) -> StatusSnapshot | None:
        """A status report from elsewhere (a downstream controller), or None: motiond's own."""
        return None

    async def wait_idle(self) -> None:
        """Wait until every queued move has been executed."""
        if not self.stepgen.idle:
            self.idle_event.clear()
            self.stepgen.request_start()
            await self.idle_event.wait()

    def new_interpreter(self, *, soft_limits: bool = True) -> Interpreter:
        """A fresh interpreter at the origin that reads G-code exactly as this machine does
        (same settings, same module codes): what ``estimate`` and ``render`` run.
        ``soft_limits=False`` previews a job whatever the travel (the toolpath)."""
        settings = self.interpreter.settings
        if not soft_limits:
            settings = replace(settings, soft_limits=False)
        interpreter = Interpreter(settings, self.codes)
        interpreter.set_position(tuple(0.0 for _ in self.core.axis_names))
        return interpreter

    def set_spin_up_delay(self, seconds: float) -> None:
        """Motion waits ``seconds`` after M3/M4 starts a stopped spindle."""
        self.spin_up_delay_s = seconds
        self.interpreter.settings = replace(self.interpreter.settings, spin_up_delay_s=seconds)

    async def sync(self, request: Sync) -> list[str]:
        """Carry out an interpreter request that needs the machine."""
        kind = request.kind
        if kind is SyncKind.HALT:
            self.emergency_stop()
            return []
        if kind is SyncKind.CLEAR_HALT:
            self.status.clear_alarm()
            return []
        if kind is SyncKind.MESSAGE:
            return list(request.params["lines"])
        handler = self.sync_handlers.get(kind)
        if handler is not None:
            return await handler(request.params)
        if kind is SyncKind.HOME:  # no module carries it out
            raise CommandError(
                Error.SETTING_DISABLED, "homing is not configured: add an [endstops] section"
            )
        await self.wait_idle()
        if kind is SyncKind.REPORT_POSITION:
            return [self.position_report()]
        return self._finish_probe(request)

    def _finish_probe(self, request: Sync) -> list[str]:
        position = self.stepgen.state.position_mm
        success = self.stepgen.probe_hit
        self.interpreter.set_position(position)
        self.planner.set_position(position)
        self.interpreter.record_probe(position, success)
        coords = ",".join(f"{v:.3f}" for v in position)
        report = f"[PRB:{coords}:{int(success)}]"
        if not success and request.params.get("error_on_fail", True):
            self.status.alarm(5, "probe fail: the probe did not change state within the move")
        return [report]

    def position_report(self) -> str:
        """Smoothie's M114 answer: work position, then machine position."""
        machine = self.stepgen.state.position_mm
        work = self.interpreter.work_position(machine)
        names = self.core.axis_names
        wpos = " ".join(f"{n}:{v:.4f}" for n, v in zip(names, work, strict=True))
        mpos = " ".join(f"{n}:{v:.4f}" for n, v in zip(names, machine, strict=True))
        return f"C: {wpos} MPos: {mpos}"

    # -- motion listener (called by the step generator) --------------------------------------
    def on_action(self, action: Action) -> None:
        events = self.status.events
        if action.name == ActionName.SPINDLE:
            self.tool.mode, self.tool.s = action.params["mode"], action.params["s"]
        elif action.name == ActionName.COOLANT:
            self.tool.flood, self.tool.mist = action.params["flood"], action.params["mist"]
        elif action.name == ActionName.PAUSE:
            self.stepgen.hold()
            self.status.set_state(MachineState.HOLD)
        elif action.name == ActionName.PROGRAM_END:
            events.emit(Event.PROGRAM_END)
            self.status.push("[MSG:Pgm End]")
        elif action.name == ActionName.MOTORS:
            events.emit(Event.MOTORS_ENABLE if action.params.get("enabled") else "motors_disable")
        events.emit(Event.ACTION, action)

    def on_idle(self) -> None:
        self.idle_event.set()
        if self.status.state in (MachineState.RUN, MachineState.JOG):
            self.status.set_state(MachineState.IDLE)

    def on_hold_stopped(self) -> None:
        if self._cancelling_jog:
            self._finish_jog_cancel()
        self.events.emit(Event.HOLD_STOPPED)

    # -- realtime commands ------------------------------------------------------------------
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

    def feed_hold(self) -> None:
        if self.status.state is MachineState.HOME:  # as in Grbl: homing ignores feed hold
            return
        if self.stepgen.idle and self.status.state is MachineState.IDLE:
            self.events.emit(Event.HOLD)  # nothing moves, but a focusing `fire` stops
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
        """Ctrl-X: stop at once, flush, keep the position; ALARM:3 if it was moving."""
        moving = self.stepgen.state.moving
        self._halt_motion()
        self.leave_check_mode()
        self.interpreter.reset()
        self.events.emit(Event.RESET)
        if moving:
            self.status.alarm(
                Alarm.ABORT_CYCLE, "reset while in motion: position may be lost, re-home"
            )
        elif self.status.state not in (MachineState.ALARM,):
            self.status.set_state(MachineState.IDLE)

    def _halt_motion(self) -> None:
        """Alarm, M112, Ctrl-X: the hardware drops what it has queued, then :meth:`stop_now`."""
        self.backend.halt()
        self.stop_now()

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
        if feed is not None:
            self.feed_override = max(10, min(200, feed))
        if rapid is not None:
            self.rapid_override = rapid
        if spindle is not None:
            self.spindle_override = max(10, min(200, spindle))
        self.planner.set_overrides(self.feed_override / 100, self.rapid_override / 100)
        self.events.emit(
            "override", self.feed_override, self.rapid_override, self.spindle_override
        )

    # -- settings and modes -----------------------------------------------------------------
    def apply_settings(self) -> None:
        """Push the live config (after ``$x=value``) into the interpreter, planner and stepgen."""
        core = self.core
        self.interpreter.settings = interpreter_settings(core, self.spin_up_delay_s)
        self.planner.settings = planner_settings(core)
        self.planner.set_overrides(self.feed_override / 100, self.rapid_override / 100)
        steps_per_mm = tuple(axis.steps_per_mm for axis in core.axes.values())
        self.stepgen.set_steps_per_mm(steps_per_mm)
        if hasattr(self.backend, "steps_per_mm"):  # sim and klipper count steps themselves
            self.backend.steps_per_mm = steps_per_mm

    def clear_offsets(self) -> None:
        """``$RST=#``: work offsets and stored positions back to zero (modal state too)."""
        position = self.interpreter.position
        self.interpreter = Interpreter(self.interpreter.settings, self.codes)
        self.interpreter.set_position(position)

    def restore_settings(self) -> None:
        self.settings.restore_defaults(self._defaults)

    def enter_check_mode(self) -> None:
        """``$C``: run lines through the interpreter without moving."""
        self._check_saved = copy.deepcopy(self.interpreter)
        self.check_mode = True
        self.status.set_state(MachineState.CHECK)

    def leave_check_mode(self) -> None:
        """Leave check mode with the modal state it had before (Grbl resets here)."""
        if not self.check_mode:
            return
        if self._check_saved is not None:
            self.interpreter = self._check_saved
            self._check_saved = None
        self.check_mode = False
        self.status.set_state(MachineState.IDLE)

    @property
    def hold_state(self) -> HoldState:
        return self.stepgen.state.hold

    # -- the task ---------------------------------------------------------------------------
    async def run(self) -> None:
        """The step generator task; also wakes writers waiting for planner room."""
        backend_task = asyncio.create_task(self.backend.run(), name="backend")
        try:
            await self.stepgen.run(
                self.clock, self._after_tick, self._backend_fault, give_turn=_give_turn
            )
        finally:
            backend_task.cancel()
            await asyncio.gather(backend_task, return_exceptions=True)
            self.backend.close()

    def _backend_fault(self, exc: Exception) -> None:
        """A tick raised: stop everything and alarm once (later failures are only logged)."""
        if self.status.alarm_code == Alarm.BACKEND_FAILED:
            log.debug("backend still failing: %r", exc)
            return
        log.error("backend failed: %r", exc, exc_info=exc)
        self.status.alarm(Alarm.BACKEND_FAILED, f"backend failed: {exc!r}")

    def _after_tick(self) -> None:
        if not self.room.is_set() and not self.planner.is_full():
            self.room.set()


_REALTIME_ACTIONS: dict[Realtime, Callable[[Machine], None]] = {
    Realtime.HOLD: Machine.feed_hold,
    Realtime.DOOR: Machine.feed_hold,
    Realtime.RESUME: Machine.cycle_start,
    Realtime.JOG_CANCEL: Machine.cancel_jog,
    Realtime.SPINDLE_STOP: Machine.spindle_stop,
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


async def _give_turn() -> None:
    """Let the event loop run every other ready callback once."""
    await asyncio.sleep(0)
