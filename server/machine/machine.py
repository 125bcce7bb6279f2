"""The motion pipeline: interpreter -> planner -> step generator -> backend, owned by the kernel.

:class:`Machine` is the default G-code handler of the dispatcher. It builds the pipeline, runs
the step generator task, listens to what motion reaches (tool state, program end, idle) and
holds the settings and modes (``$x=``, ``$RST``, ``$C``). Its two other parts are base classes
in their own modules, on the same state:

* :class:`~server.machine.feed.GcodeFeed` takes lines in: it runs the interpreter,
  feeds moves and ordered actions to the planner (waiting while it is full: that wait is the
  flow control that delays a sender's ``ok``) and carries out the interpreter's sync requests;
* :class:`~server.machine.controls.RealtimeCommands` acts at once: hold, resume, reset,
  jog cancel, overrides, M112.
"""

from __future__ import annotations

import asyncio
import copy
import logging
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from server.config import Config
from server.errors import Alarm, BackendFault, CommandError, Error
from server.gcode.codes import CodeTable
from server.gcode.interpreter import Interpreter
from server.gcode.parser import Line
from server.machine.controls import RealtimeCommands
from server.machine.feed import GcodeFeed
from server.machine.parts import interpreter_settings, planner_settings
from server.machine.settings import Settings
from server.motion.backend import Backend
from server.motion.motion_state import HoldState
from server.motion.moves import Action, ActionName, SyncKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from server.paths import settings_path
from server.protocol.reports import StatusSnapshot
from server.runtime.clock import Clock, VirtualClock
from server.runtime.dispatcher import Command, Dispatcher
from server.runtime.events import Event, EventBus, MachineState
from server.runtime.state import MachineStatus
from server.runtime.ticks import TickWatch, run_ticks

log = logging.getLogger("motiond.machine")


@dataclass(slots=True)
class ToolState:
    """The spindle/laser and coolant state as motion last reached it."""

    mode: ToolMode = ToolMode.OFF
    s: float = 0.0
    flood: bool = False
    mist: bool = False


SyncHandler = Callable[[dict[str, Any]], Awaitable[list[str]]]


class Machine(GcodeFeed, RealtimeCommands):
    """Owns the motion pipeline; see the module docstring."""

    counts_blocks = True  # the step generator's blocks_done counts the blocks executed
    reads_spans = True  # a job's plain lines may come as spans (handle_span)

    def __init__(self, config: Config, clock: Clock, events: EventBus, status: MachineStatus,
                 backend: Backend) -> None:
        core = config.core
        self.clock, self.events, self.status = clock, events, status
        status.stop_motion, status.before_unlock = self._halt_motion, self.leave_check_mode
        self.core = core
        self.backend = backend
        self.backend.watch_position(self.relocate)
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
        self._work = asyncio.Event()  # motion may start: the step generator stops sleeping
        self.stepgen.wake = self._work.set
        self.tick_watch: TickWatch | None = None  # told of the ticks on real time (the kernel's)
        self.backend.wake_with(self._backend_wake)  # a fault or an output on: ticks again
        self.idle_event = asyncio.Event()
        self.idle_event.set()
        self.check_mode = False
        self.epoch = 0  # incremented by every halt/reset; lines waiting across one are dropped
        self.tool = ToolState()
        self._cancelling_jog = False
        self._idle_timer: asyncio.TimerHandle | None = None
        self._check_saved: Interpreter | None = None
        self._defaults = core.model_copy(deep=True)
        self.feed_override = 100
        self.rapid_override = 100
        self.spindle_override = 100
        self.settings = Settings(  # last: it applies saved values
            core, settings_path(config),
            is_idle=lambda: self.stepgen.idle, apply=self.apply_settings,
        )

    # -- what the machine is ---------------------------------------------------------------
    @property
    def busy(self) -> bool:
        """Motion is queued or running (its source owns the machine until it ends)."""
        return not self.stepgen.idle

    async def write_setting(self, command: Command) -> list[str]:
        """``$x=value``: checked, applied live and saved (a downstream board: its own)."""
        before = self.settings.snapshot()
        self.settings.write(command.args)
        try:
            await asyncio.to_thread(self.settings.save, self.settings.file_text())
        except OSError as exc:
            self.settings.restore(before)
            log.warning("$%s not saved to %s: %s", command.args, self.settings.path, exc)
            raise CommandError(Error.SETTING_NOT_SAVED,
                               f"${command.args} not saved ({exc.strerror}): the old value "
                               "is kept") from exc
        return []

    def register_commands(self, dispatcher: Dispatcher) -> None:
        """Commands this machine adds to the core's (a downstream controller's); none here."""

    async def board_answer(self, command: Command) -> list[str] | None:
        """A downstream controller's own answer to ``$$``, ``$#``, ``$G``, ``$I``, ``$N``,
        ``$N0=``/``$N1=``; None: motiond answers (always, here)."""
        return None

    async def jog(self, command: Command, line: Line) -> None:
        """``$J=`` (checked for the state, parsed): the jog planned like any move."""
        for move in self.interpreter.jog(line):
            await self.queue_move(move)
        self.stepgen.request_start()

    def status_snapshot(self, rx_free_bytes: int) -> StatusSnapshot | None:
        """A status report from elsewhere (a downstream controller), or None: motiond's own."""
        return None

    def new_interpreter(self, *, soft_limits: bool = True, live: bool = False) -> Interpreter:
        """An interpreter that reads G-code exactly as this machine does (same settings, same
        module codes): what ``estimate`` and ``render`` run. A fresh one at the origin, or with
        ``live`` a copy of the machine's own (its position, work offsets and modal state: what
        a job started now begins from). ``soft_limits=False`` reads a job whatever the travel
        (the toolpath, the time; fit is checked apart, :mod:`server.offline.fit`)."""
        settings = self.interpreter.settings
        if not soft_limits:
            settings = replace(settings, soft_limits=False)
        if live:
            interpreter = copy.deepcopy(self.interpreter)
            interpreter.settings = settings
            return interpreter
        interpreter = Interpreter(settings, self.codes)
        interpreter.set_position(tuple(0.0 for _ in self.core.axis_names))
        return interpreter

    def set_spin_up_delay(self, seconds: float) -> None:
        """Motion waits ``seconds`` after M3/M4 starts a stopped spindle."""
        self.spin_up_delay_s = seconds
        self.interpreter.settings = replace(self.interpreter.settings, spin_up_delay_s=seconds)

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
            self.motors(bool(action.params.get("enabled")))
        events.emit(Event.ACTION, action)

    def motors(self, enabled: bool) -> None:
        """M17 / M18, M84, ``$SLP``: the stepper drivers on or off where motion is now."""
        self.backend.motors(enabled, self.clock.now_s())
        self.events.emit(Event.MOTORS_ENABLE if enabled else Event.MOTORS_DISABLE)

    def on_idle(self) -> None:
        """Motion has ended in the step generator: the machine is idle once the hardware has
        carried it out too (a Klipper MCU's last step comes a lead time later)."""
        if self._idle_timer is not None:
            self._idle_timer.cancel()
            self._idle_timer = None
        wait_s = self.backend.done_at_s() - self.clock.now_s()
        if wait_s > 0.0:
            self._idle_timer = asyncio.get_running_loop().call_later(wait_s, self._idle_later)
            return
        self.idle_event.set()
        if self.status.state in (MachineState.RUN, MachineState.JOG):
            self.status.set_state(MachineState.IDLE)

    def _idle_later(self) -> None:
        self._idle_timer = None
        if self.stepgen.idle:  # no new motion meanwhile (it ends with an on_idle of its own)
            self.on_idle()

    def on_hold_stopped(self) -> None:
        if self._cancelling_jog:
            self._finish_jog_cancel()
        self.events.emit(Event.HOLD_STOPPED)

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
        """The step generator task; also wakes writers waiting for planner room. On real time
        the tick sleeps while nothing moves; on a virtual clock it always ticks, since the
        clock's time runs only as fast as its sleepers (file reads in threads would otherwise
        see seconds jump by)."""
        backend_task = asyncio.create_task(self.backend.run(), name="backend")
        sleeps = not isinstance(self.clock, VirtualClock)
        try:
            await run_ticks(
                self.stepgen, self.clock, self._after_tick, self._backend_fault,
                give_turn=_give_turn,
                wait_for_work=self._wait_for_work if sleeps else None,
                watch=self.tick_watch if sleeps else None,
            )
        finally:
            backend_task.cancel()
            await asyncio.gather(backend_task, return_exceptions=True)
            self.backend.close()

    def _backend_wake(self) -> None:
        """The backend needs a sample soon (a fault to report, an output to send): the ticks
        resume if they slept, and the next comes at once if they are sparse."""
        self._work.set()
        self.stepgen.hurry(0.0)

    async def _wait_for_work(self) -> None:
        """Until the step generator is woken (checked and cleared in one turn: no race)."""
        self._work.clear()
        rest = getattr(self.backend, "rest", None)  # a backend whose I/O the ticks sample
        if rest is not None:
            rest()
        await self._work.wait()

    def _backend_fault(self, exc: Exception) -> None:
        """A tick raised: stop everything and alarm once (later failures are only logged).
        An expected hardware fault (:class:`BackendFault`) is one line with its reason; one
        while the machine is in ALARM already is told, the alarm in force stays."""
        if self.status.alarm_code == Alarm.BACKEND_FAILED:
            log.debug("backend still failing: %r", exc)
            return
        if not isinstance(exc, BackendFault):
            log.error("backend failed: %r", exc, exc_info=exc)
            self.status.alarm(Alarm.BACKEND_FAILED, f"backend failed: {exc!r}")
        elif self.status.state is MachineState.ALARM:
            self.status.push(f"[MSG:{exc}]")
        else:
            self.status.alarm(Alarm.BACKEND_FAILED, f"backend failed: {exc}")

    async def unlock(self) -> None:
        """``$X`` / M999: the hardware is made usable again first (CommandError if it
        cannot be: the alarm stays), then the alarm is cleared."""
        if self.status.state is MachineState.ALARM:
            await self.backend.recover()
        self.status.clear_alarm()

    def position_now_mm(self) -> tuple[float, ...]:
        """Where the tool is now: what the hardware has carried out where it runs behind the
        step generator (a Klipper MCU), else the step generator's position."""
        executed = self.backend.position_at_mm(self.clock.now_s())
        return self.stepgen.state.position_mm if executed is None else tuple(executed)

    def speed_now_mm_s(self) -> float:
        """The path speed now: the hardware's where it runs behind the step generator."""
        executed = self.backend.speed_at_mm_s(self.clock.now_s())
        return self.stepgen.state.speed_mm_s if executed is None else executed

    def relocate(self, position_mm: Sequence[float]) -> None:
        """The hardware stopped at ``position_mm`` (not where motion was planned to be):
        that is the machine position now."""
        self.set_machine_position(tuple(position_mm))

    def _after_tick(self) -> None:
        if not self.room.is_set() and self.planner.has_room():
            self.room.set()


async def _give_turn() -> None:
    """Let the event loop run every other ready callback once."""
    await asyncio.sleep(0)
