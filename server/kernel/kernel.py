"""The kernel: config, clock, events, the module registry and its supervision, machine state.

The kernel owns every long-lived task of the core in one TaskGroup: the step generator, the
second ticker and one supervised task per module. A module whose ``run()`` raises puts the
machine in ALARM (motion stopped, tools off) with a message naming the module and the error;
the server stays up and keeps answering.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from pydantic import BaseModel

from server.backends.build import build_backend
from server.backends.grbl.machine import GrblMachine
from server.config import Config, ModuleSpec
from server.errors import Alarm, ConfigError
from server.gcode.codes import CodeConflict, CodeFactory
from server.jobs.jobs import Jobs
from server.kernel.commands import CoreCommands
from server.kernel.control import MachineControl
from server.kernel.loop_monitor import LoopMonitor
from server.kernel.module import ApiHandler, ApiMethod, ApiParams, Module
from server.kernel.status import build_status
from server.machine.machine import Machine, SyncHandler
from server.machine.settings import Setting
from server.motion.motion_state import MotionState
from server.motion.moves import Action, Move, Position, SyncKind
from server.motion.pieces import PowerOf
from server.protocol.reports import format_lock
from server.runtime.clock import Clock, on_grid_s
from server.runtime.dispatcher import Dispatcher, Handler, SystemSource
from server.runtime.events import Event, EventBus, MachineState
from server.runtime.gcpacer import GcPacer
from server.runtime.ratelimit import (
    REALTIME_TOTAL_BURST_BYTES,
    TOTAL_BURST_BYTES,
    input_budget,
    realtime_allowance,
)
from server.runtime.state import MachineStatus

log = logging.getLogger("motiond.kernel")


class _Outputs:
    """Output pins, set at the kernel clock's now (implements server.kernel.module.Outputs)."""

    def __init__(self, machine: Machine, clock: Clock) -> None:
        self._machine, self._clock = machine, clock

    def set(self, pin: str, value: float) -> None:
        time_s = self._machine.stepgen.motion_time_s(self._clock.now_s())
        self._machine.backend.set_output(pin, value, time_s)

    def follow_motion(self, pin: str, power_of: PowerOf, period_s: float) -> bool:
        """Where the backend times ``pin`` from the trajectory itself (a Klipper MCU), each
        block's power comes from ``power_of`` and True is returned; else False (the caller
        samples the motion and sets the pin)."""
        follow = getattr(self._machine.backend, "follow_power", None)
        if follow is None or not follow(pin, period_s):
            return False
        self._machine.stepgen.follow_power(power_of)
        return True

    def value(self, pin: str) -> float:
        return self._machine.backend.output(pin)

    def declare_tool(self, pin: str) -> None:
        self._machine.backend.declare_tool(pin)


class _Inputs:
    """Switch inputs (implements server.kernel.module.Inputs)."""

    def __init__(self, machine: Machine) -> None:
        self._machine = machine

    def switch_triggered(self, name: str) -> bool:
        return self._machine.backend.switch_triggered(name)

    def place_switch(self, name: str, at_mm: float) -> None:
        self._machine.backend.place_switch(name, at_mm)


class _Motion:
    """Moves outside G-code and motion controls (implements server.kernel.module.Motion)."""

    def __init__(self, machine: Machine) -> None:
        self._machine = machine
        self.tick_s = 1.0 / machine.core.stepgen.tick_hz

    async def queue_move(self, move: Move) -> None:
        await self._machine.queue_move(move)

    async def wait_idle(self) -> None:
        await self._machine.wait_idle()

    def stop_now(self) -> None:
        self._machine.stop_now()

    def set_position(self, position_mm: Position) -> None:
        self._machine.set_machine_position(position_mm)


class _Context:
    """A module's handle on the kernel (implements server.kernel.module.ModuleContext)."""

    def __init__(self, kernel: Kernel, name: str) -> None:
        self._kernel = kernel
        self.name = name
        self.log = logging.getLogger(f"motiond.module.{name}")
        self.clock = kernel.clock
        self.core = kernel.config.core
        self.outputs = _Outputs(kernel.machine, kernel.clock)
        self.inputs = _Inputs(kernel.machine)
        self.moves = _Motion(kernel.machine)
        self.control = kernel.control
        self._source = SystemSource(f"module {name}")

    def register_command(
        self, name: str, handler: Handler, *, when_locked: bool = False, query: bool = False
    ) -> None:
        self._kernel.dispatcher.register(name, handler, when_locked=when_locked, query=query)

    def register_code(
        self,
        code: int,
        factory: CodeFactory,
        *,
        group: str | None = None,
        uses: str = "",
        query: bool = False,
        key: tuple[str, str] | None = None,
    ) -> None:
        self._kernel.machine.codes.register(
            self.name, code, factory, group=group, uses=uses, query=query, key=key
        )

    def register_sync(self, kind: SyncKind, handler: SyncHandler) -> None:
        self._kernel.machine.sync_handlers[kind] = handler

    def set_spin_up_delay(self, seconds: float) -> None:
        self._kernel.machine.set_spin_up_delay(seconds)

    async def run_gcode(self, text: str, ticket: int | None = None) -> list[str]:
        return await self._kernel.dispatcher.submit(text, self._source, ticket)

    def run_in_job(self, text: str, ticket: int) -> asyncio.Future[list[str] | None] | None:
        return self._kernel.jobs.interject(text, ticket)

    async def start_job(self, name: str, ticket: int | None = None) -> None:
        await self._kernel.jobs.start(name, ticket)

    def ticket(self) -> int:
        return self._kernel.status.ticket()

    def still_valid(self, ticket: int) -> bool:
        return self._kernel.status.still_valid(ticket)

    def status(self) -> dict[str, Any]:
        return build_status(self._kernel)

    def register_api_method(
        self,
        name: str,
        handler: ApiHandler,
        params: type[BaseModel] = ApiParams,
        *,
        control: bool = False,
    ) -> None:
        if name in self._kernel.api_methods:
            raise ValueError(f"[{self.name}]: JSON-RPC method {name} is defined twice")
        self._kernel.api_methods[name] = ApiMethod(name, handler, params, control)

    def add_status_field(self, name: str, read: Callable[[], Any]) -> None:
        self._kernel.status_fields[name] = read

    def add_feature(self, name: str) -> None:
        self._kernel.features.add(name)

    def register_setting(self, number: int, description: str, read: Callable[[], float],
                         write: Callable[[float], None], *, high: float) -> None:
        setting = Setting(number, description, lambda core: read(),
                          lambda core, value: write(value), high=high)
        self._kernel.machine.settings.adopt(setting)

    def subscribe(self, event: str, callback: Callable[..., None]) -> None:
        self._kernel.events.subscribe(event, callback)

    def lookup(self, name: str) -> Module:
        return self._kernel.modules[name]

    def motion(self) -> MotionState:
        return self._kernel.machine.stepgen.state

    async def queue_action(self, action: Action) -> None:
        await self._kernel.machine.queue_action(action)

    def alarm(self, message: str, code: int = Alarm.MODULE_FAILED) -> None:
        self._kernel.alarm(code, f"{self.name}: {message}")

    def emit(self, event: str, *args: Any) -> None:
        self._kernel.events.emit(event, *args)

    def set_state(self, state: MachineState) -> None:
        self._kernel.set_state(state)

    def clear_alarm(self) -> None:
        self._kernel.clear_alarm()


# $X / Ctrl-X to leave (a tuple: membership by identity, without the enum's Python-level hash)
LOCKED_STATES = (MachineState.ALARM, MachineState.SLEEP)
QUIET_AFTER_S = 1.0  # no command for this long (and nothing moving): the loop monitor slows


class Kernel:
    """Owns the machine state and every core task."""

    def __init__(self, config: Config, clock: Clock) -> None:
        self.config = config
        self.clock = clock
        self.events = EventBus()
        self.status = MachineStatus(self.events)
        machine_class = GrblMachine if config.core.backend.kind == "grbl" else Machine
        self.machine = machine_class(config, clock, self.events, self.status,
                                     build_backend(config.core))
        self.dispatcher = Dispatcher(
            is_locked=lambda: self.status.state in LOCKED_STATES,
            is_busy=lambda: self.machine.busy or self.jobs.active,
            stops=self.status.ticket,
            locked_by=self._locked_by,
        )
        self.dispatcher.set_gcode_handler(
            self.machine.handle_gcode, lambda line: self.machine.interpreter.classify(line),
            self.machine.handle_span if self.machine.reads_spans else None,
        )
        self.jobs = Jobs(self)
        self.control = MachineControl(self.machine, self.jobs)
        # what all connections that may not control may send together (see sessions.input)
        self.read_only_input = input_budget(
            config.core.protocol.read_only_input_total_bytes_per_s, TOTAL_BURST_BYTES)
        # the realtime bytes all flooding connections may have examined together
        self.realtime_input = realtime_allowance(
            config.core.protocol.realtime_total_bytes_per_s, REALTIME_TOTAL_BURST_BYTES)
        self.modules: dict[str, Module] = {}
        self.api_methods: dict[str, ApiMethod] = {}  # contributed by modules
        self.status_fields: dict[str, Callable[[], Any]] = {}
        self.features: set[str] = set()
        self._specs: dict[str, ModuleSpec] = {}
        commands = CoreCommands(self)
        commands.register(self.dispatcher)
        self.machine.register_commands(self.dispatcher)
        self._load_modules(config)
        commands.register_fallbacks(self.dispatcher)
        self.loop_monitor = LoopMonitor(  # as often as the step generator ticks, at most 1 kHz
            period_s=max(0.001, self.machine.stepgen.tick_s),
            gc_pacer=GcPacer(lambda: not self.machine.stepgen.idle), is_quiet=self._quiet)
        self.machine.tick_watch = self.loop_monitor  # it rides the ticks while they run
        self._stop = asyncio.Event()
        self.started = asyncio.Event()
        self.stopped = False

    def _load_modules(self, config: Config) -> None:
        """Instantiate every configured module; claims of one code by two are config errors."""
        problems: list[str] = []
        for spec in config.modules:
            try:
                self.modules[spec.section] = spec.cls(_Context(self, spec.section), spec.config)
            except CodeConflict as exc:
                problems.append(f"{_label(config)}: [{spec.section}]: {exc}")
            self._specs[spec.section] = spec
        if problems:
            raise ConfigError(problems)

    # -- machine state (owned by self.status) ---------------------------------------------
    @property
    def state(self) -> MachineState:
        return self.status.state

    @property
    def alarm_code(self) -> int:
        return self.status.alarm_code

    def _locked_by(self) -> str:
        """What locks G-code out, for a refused line: ``ALARM:40 (meaning)`` or ``Sleep``."""
        if self.status.state is MachineState.ALARM:
            return format_lock(self.status.alarm_code)
        return str(self.status.state.value)

    @property
    def alarm_message(self) -> str:
        return self.status.alarm_message

    def set_state(self, state: MachineState) -> None:
        self.status.set_state(state)

    def push(self, message: str) -> None:
        """Send an unsolicited line (``ALARM:2``, ``[MSG:...]``) to every connection."""
        self.status.push(message)

    def alarm(self, code: int, message: str) -> None:
        """Stop motion and tools at once, lock G-code out, tell everyone why."""
        self.status.alarm(code, message)

    def clear_alarm(self) -> None:
        """``$X`` / ``M999``: unlock after an alarm."""
        self.status.clear_alarm()

    # -- tasks -----------------------------------------------------------------------------
    async def run(self) -> None:
        """Run the step generator, the second ticker and every module until :meth:`stop`."""
        async with asyncio.TaskGroup() as group:
            tasks = [
                group.create_task(self.machine.run(), name="stepgen"),
                group.create_task(self._second_ticker(), name="second"),
                group.create_task(self.loop_monitor.run(), name="loop-monitor"),
            ]
            for section, module in self.modules.items():
                tasks.append(group.create_task(self._supervise(section, module), name=section))
            self.started.set()
            await self._stop.wait()
            self.machine.stop_now()
            await self.jobs.close()
            for task in tasks:
                task.cancel()
        self.stopped = True

    def _quiet(self) -> bool:
        """Nothing moves and no command came for a second."""
        return (self.machine.stepgen.can_sleep
                and time.monotonic() - self.dispatcher.last_command_s > QUIET_AFTER_S)

    def stop(self) -> None:
        """Ask :meth:`run` to end: tools off, motion stopped, tasks cancelled. Repeatable."""
        if not self._stop.is_set():
            self.dispatcher.close()
            self.machine.stop_now()
            self.events.emit(Event.SHUTDOWN)
            self._stop.set()

    async def _supervise(self, section: str, module: Module) -> None:
        try:
            await module.run()
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # noqa: BLE001 - supervision: any failure alarms the machine
            log.exception("module [%s] crashed", section)
            self.alarm(Alarm.MODULE_FAILED, f"module [{section}] failed: {exc!r}")

    async def _second_ticker(self) -> None:
        next_s = on_grid_s(self.clock.now_s(), 1.0)  # whole seconds: with other wake-ups
        while True:
            await self.clock.sleep_until(next_s)
            self.events.emit(Event.SECOND, next_s)
            next_s += 1.0


def _label(config: Config) -> str:
    return str(config.path) if config.path else "<default config>"
