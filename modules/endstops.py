"""``[endstops]``: limit switches, hard limits, ``M119`` and homing (``$H``, ``G28.2``).

One switch per configured axis, at the end the axis homes to (``direction``). With the
simulated backend, ``switch_at_mm`` places it (``x_min``/``x_max``, in the sim's physical
coordinates: where the steps put the tool); an axis without it has no switch there, and homing
it fails.

Homing (``$H``, ``$HX``..., ``G28.2 [X Y Z]``; allowed in ALARM, state ``Home`` meanwhile) runs
the axes in ``order`` groups, lowest first; the axes of one group move together. Per group, as
Grbl: seek towards the switches at ``seek_mm_s`` for up to 1.5 x travel, pull off by
``pull_off_mm``, locate slowly at ``feed_mm_s`` (up to 5 x pull-off), pull off again, and set
the axis' machine position to its ``min_mm`` (or ``max_mm``) there, as FluidNC does: the whole
travel lies off the switch. A watcher at ``check_hz`` stops motion as soon as a switch triggers.
Failures raise Grbl's alarms: 6 homing aborted (reset, hold, halt), 8 the pull-off did not
clear the switch, 9 the switch was not found within the search distance.

Outside homing, a switch that becomes active while the machine moves raises ALARM:1 (hard
limit; edge-triggered as Grbl, so one may jog off a pressed switch after ``$X``). ``M119``
answers ``X_min:0 Y_min:1 ...`` and the status report's ``Pn:`` shows active switches.

An axis stays homed (``homed`` in the status) until its position may be lost, as Klipper
forgets it: motors off (``M84``/``M18``, ``$SLP``, Klipper's restarts), an alarm that stops
motion abruptly or says the position may be lost (emergency stop, hard limit, reset in motion,
a failed homing, module or backend), and at the start of its own homing. A soft limit or a
failed probe keeps it (the position is kept).

    [endstops]
    hard_limits = true
    axes.x = { direction = "min", seek_mm_s = 50, feed_mm_s = 5, pull_off_mm = 2, order = 2 }
    axes.y = { direction = "min", order = 2 }
    axes.z = { direction = "max", order = 1, switch_at_mm = 3 }
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Any, Literal

from pydantic import Field

from server.errors import Alarm, CommandError, ConfigError, Error
from server.gcode.codes import CodeCall
from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.motion.moves import Move, MoveKind, Output, Position, Sync, SyncKind
from server.runtime.clock import VirtualClock
from server.runtime.dispatcher import Command
from server.runtime.events import Event, MachineState

LOCKED = 9
SEEK_SCALE = 1.5  # Grbl: search up to 1.5 x the travel
LOCATE_SCALE = 5.0  # Grbl: locate within 5 x the pull-off
# States in which nothing moves: the switch watcher rests until the state changes.
RESTING_STATES = frozenset({MachineState.IDLE, MachineState.ALARM, MachineState.SLEEP})
# Alarms after which the position is still what it was (Grbl: "position retained").
POSITION_KEPT = frozenset({Alarm.SOFT_LIMIT, Alarm.PROBE_INITIAL, Alarm.PROBE_CONTACT})


class AxisEndstop(ModuleConfig):
    direction: Literal["min", "max"] = "min"
    seek_mm_s: float = Field(50.0, gt=0, description="search speed (Grbl $25)")
    feed_mm_s: float = Field(5.0, gt=0, description="locate speed (Grbl $24)")
    pull_off_mm: float = Field(2.0, gt=0, le=100, description="Grbl $27")
    order: int = Field(1, ge=0, description="homing group: lower groups home first")
    switch_at_mm: float | None = Field(None, description="sim backend: where the switch is")


class EndstopsConfig(ModuleConfig):
    axes: dict[str, AxisEndstop] = Field(min_length=1)
    hard_limits: bool = True
    check_hz: float = Field(1000.0, ge=10, le=100_000)
    debounce_s: float = Field(0.05, ge=0, le=5, description="pause after each phase (Grbl $26)")


class HomingFailed(Exception):
    """A homing phase failed; ``code`` is the Grbl alarm to raise."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


class _Axis:
    """One axis' switch and homing parameters, resolved against the machine (the direction
    read when asked: Grbl's ``$23`` changes it)."""

    def __init__(self, name: str, index: int, cfg: AxisEndstop, min_mm: float,
                 max_mm: float) -> None:
        self.name, self.index, self.cfg = name, index, cfg
        self.min_mm, self.max_mm = min_mm, max_mm
        self.travel_mm = max_mm - min_mm

    @property
    def switch(self) -> str:
        return f"{self.name.lower()}_{self.cfg.direction}"

    @property
    def sign(self) -> float:
        """+1 or -1: the way towards the switch."""
        return -1.0 if self.cfg.direction == "min" else 1.0

    @property
    def home_mm(self) -> float:
        return self.min_mm if self.cfg.direction == "min" else self.max_mm


class Endstops(Module):
    """Switch watcher, M119 and the homing cycle; see the module docstring."""

    name = "endstops"
    Config = EndstopsConfig

    def __init__(self, ctx: ModuleContext, config: EndstopsConfig) -> None:
        super().__init__(ctx, config)
        self.config: EndstopsConfig = config
        self.axes = self._resolve_axes()
        for axis in self.axes:
            if axis.cfg.switch_at_mm is not None:
                ctx.inputs.place_switch(axis.switch, axis.cfg.switch_at_mm)
        self.homing = False
        self.homed: set[str] = set()
        self._state = MachineState.IDLE
        self._abort: str | None = None
        self._active: set[str] = set()
        self._wake = asyncio.Event()  # a state change: the resting watcher resumes
        for name in ("$H", *(f"$H{axis.name}" for axis in self.axes)):
            ctx.register_command(name, self._home_command, when_locked=True)
        ctx.register_sync(SyncKind.HOME, self._home_sync)
        ctx.add_feature("homing")
        grbl_settings(ctx, self.config, self.axes)
        ctx.register_code(119, self._m119, query=True)
        ctx.subscribe(Event.STATE, self._on_state)
        ctx.subscribe(Event.MOTORS_DISABLE, self.forget_homing)
        ctx.subscribe(Event.HALT, self._on_halt)

    def _resolve_axes(self) -> list[_Axis]:
        core = self.ctx.core
        names = core.axis_names
        problems = [f"[endstops.axes.{key}]: no such axis (axes: {', '.join(names)})"
                    for key in self.config.axes if key.upper() not in names]
        if problems:
            raise ConfigError(problems)
        axes = []
        for key, cfg in self.config.axes.items():
            limits = core.axes[next(k for k in core.axes if k.upper() == key.upper())]
            index = names.index(key.upper())
            axes.append(_Axis(key.upper(), index, cfg, limits.min_mm, limits.max_mm))
        return axes

    # -- switches --------------------------------------------------------------------------
    def triggered(self, axes: Sequence[_Axis] | None = None) -> list[_Axis]:
        """The axes (of ``axes``, default all) whose switch is active now."""
        inputs = self.ctx.inputs
        return [a for a in axes or self.axes if inputs.switch_triggered(a.switch)]

    def report_pins(self) -> str:
        return "".join(axis.name for axis in self.triggered())

    def _m119(self, call: CodeCall) -> list[Output]:
        active = {axis.name for axis in self.triggered()}
        line = " ".join(f"{a.name}_{a.cfg.direction}:{int(a.name in active)}" for a in self.axes)
        return [Sync(SyncKind.MESSAGE, {"lines": [line]})]

    async def run(self) -> None:
        """Watch the switches at ``check_hz``: a switch becoming active while moving is ALARM:1.
        While nothing can move (idle, alarm, sleep) the watcher waits for a state change, then
        takes the switches as they are (one pressed by hand meanwhile is not a new trigger); on
        real time only, as the step generator's tick."""
        clock = self.ctx.clock
        period_s = 1.0 / self.config.check_hz
        next_s = clock.now_s()
        may_rest = not isinstance(clock, VirtualClock)  # as the step generator's tick
        while True:
            if may_rest and self._resting():
                self._wake.clear()
                await self._wake.wait()
                self._active = {axis.switch for axis in self.triggered()}
                next_s += (clock.now_s() - next_s) // period_s * period_s  # same phase
            next_s += period_s
            await clock.sleep_until(next_s)
            next_s = max(next_s, clock.now_s() - 0.25)
            if self.homing:
                continue
            active = {axis.switch for axis in self.triggered()}
            new = active - self._active
            self._active = active
            if new and self.config.hard_limits and self.ctx.motion().moving:
                self.ctx.alarm(f"hard limit: {', '.join(sorted(new))} triggered",
                               Alarm.HARD_LIMIT)

    def _resting(self) -> bool:
        return (self._state in RESTING_STATES and not self.homing
                and not self.ctx.motion().moving)

    def _on_state(self, state: MachineState) -> None:
        self._state = state
        self._wake.set()
        if self.homing and state is not MachineState.HOME and self._abort is None:
            self._abort = f"homing aborted (machine went to {state.value})"

    def forget_homing(self) -> None:
        """Every axis unhomed: its position may no longer be where the steps say."""
        if self.homed:
            self.ctx.log.info("homing lost: %s", ", ".join(sorted(self.homed)))
        self.homed.clear()

    def _on_halt(self, _reason: str) -> None:
        """An alarm loses homing unless it kept the position (:data:`POSITION_KEPT`); a halt
        without an alarm (a job's abort, M410) keeps it."""
        alarm = self.ctx.status().get("alarm")
        if alarm is not None and alarm.get("code") not in POSITION_KEPT:
            self.forget_homing()

    # -- homing ----------------------------------------------------------------------------
    async def _home_command(self, command: Command) -> list[str]:
        """``$H`` or ``$HX``."""
        return await self._home_axes(self._axes_named(set(command.name[2:])))

    async def _home_sync(self, params: dict[str, Any]) -> list[str]:
        """``G28.2 [X Y Z]``, from the interpreter (axis indices; none: every axis)."""
        names = self.ctx.core.axis_names
        return await self._home_axes(self._axes_named({names[i] for i in params["axes"]}))

    async def _home_axes(self, axes: list[_Axis]) -> list[str]:
        if not self.ctx.core.machine.homing:
            raise CommandError(Error.SETTING_DISABLED, "homing is disabled: $22=1 enables it")
        if self._state in (MachineState.IDLE, MachineState.RUN):
            await self.ctx.moves.wait_idle()  # a streamed G28.2 runs after the moves before it
        if self._state not in (MachineState.IDLE, MachineState.ALARM):
            raise CommandError(
                Error.NOT_IDLE, f"homing needs an idle machine, not {self._state.value}"
            )
        try:
            await self.home(axes)
        except HomingFailed as exc:
            if self._state is not MachineState.ALARM:  # (a reset raised ALARM:6 itself)
                self.ctx.alarm(str(exc), exc.code)
            raise CommandError(LOCKED, f"homing failed: ALARM:{exc.code}") from exc
        return [f"[MSG:Homed {''.join(axis.name for axis in axes)}]"]

    def _axes_named(self, letters: set[str]) -> list[_Axis]:
        """The endstop axes named (none named: all of them)."""
        unknown = letters - {axis.name for axis in self.axes}
        if unknown:
            named = "".join(sorted(unknown))
            raise CommandError(
                Error.INVALID_STATEMENT, f"{named}: no homing switch ([endstops] axes): "
                "an axis without one needs no homing, its position is kept from start-up")
        return [axis for axis in self.axes if axis.name in letters or not letters]

    async def home(self, axes: Sequence[_Axis]) -> None:
        """Home ``axes`` group by group; raise :class:`HomingFailed` with the Grbl alarm code."""
        if self._state is MachineState.ALARM:
            self.ctx.clear_alarm()
        self._abort = None
        self.ctx.set_state(MachineState.HOME)
        self.homing = True
        self.homed.difference_update(axis.name for axis in axes)  # homed again, or not at all
        try:
            for order in sorted({axis.cfg.order for axis in axes}):
                await self._home_group([axis for axis in axes if axis.cfg.order == order])
        finally:
            self.homing = False
            self._active = {axis.switch for axis in self.triggered()}
            if self._state is MachineState.HOME:
                self.ctx.set_state(MachineState.IDLE)

    async def _home_group(self, group: list[_Axis]) -> None:
        seek = min(axis.cfg.seek_mm_s for axis in group)
        feed = min(axis.cfg.feed_mm_s for axis in group)
        await self._seek(group, seek, lambda a: a.travel_mm * SEEK_SCALE)
        await self._pull_off(group, seek)
        await self._seek(group, feed, lambda a: a.cfg.pull_off_mm * LOCATE_SCALE)
        await self._pull_off(group, seek)
        position = list(self.ctx.motion().position_mm)
        for axis in group:
            position[axis.index] = axis.home_mm
            self.homed.add(axis.name)
        self.ctx.moves.set_position(tuple(position))

    async def _seek(self, group: list[_Axis], speed: float,
                    distance: Callable[[_Axis], float]) -> None:
        remaining = list(group)
        while remaining:
            target = list(self.ctx.motion().position_mm)
            for axis in remaining:
                target[axis.index] += axis.sign * distance(axis)
            hit = await self._move(tuple(target), speed, remaining)
            if not hit:
                names = ", ".join(axis.switch for axis in remaining)
                raise HomingFailed(Alarm.HOMING_NOT_FOUND, f"homing: {names} switch not found")
            remaining = [axis for axis in remaining if axis not in hit]

    async def _pull_off(self, group: list[_Axis], speed: float) -> None:
        target = list(self.ctx.motion().position_mm)
        for axis in group:
            target[axis.index] -= axis.sign * axis.cfg.pull_off_mm
        await self._move(tuple(target), speed, [])
        still = self.triggered(group)
        if still:
            names = ", ".join(axis.switch for axis in still)
            raise HomingFailed(Alarm.HOMING_PULL_OFF, f"homing: pull-off did not clear {names}")

    async def _move(self, target: Position, speed: float, watch: list[_Axis]) -> list[_Axis]:
        """Move to ``target``; stop at once when a switch of ``watch`` triggers (returned)."""
        moves, clock = self.ctx.moves, self.ctx.clock
        hit = self.triggered(watch) if watch else []
        if hit:
            return hit
        await moves.queue_move(Move(target, speed, MoveKind.HOMING))
        waiter = asyncio.create_task(moves.wait_idle())
        try:
            next_s = clock.now_s()
            while not waiter.done():
                self._check_abort()
                hit = self.triggered(watch) if watch else []
                if hit:
                    moves.stop_now()
                    break
                next_s += 1.0 / self.config.check_hz
                await clock.sleep_until(next_s)
        finally:
            waiter.cancel()
        await self._settle()
        return hit or (self.triggered(watch) if watch else [])

    async def _settle(self) -> None:
        """Debounce, and let the step generator see an empty queue for a few ticks.

        The ticks also clear the generator's stale time into the stopped block, which
        ``StepGenerator.stop_now`` leaves behind (see the report: core fix needed).
        """
        tick_s = self.ctx.moves.tick_s
        clock = self.ctx.clock
        await clock.sleep_until(clock.now_s() + max(self.config.debounce_s, 3 * tick_s))
        self._check_abort()

    def _check_abort(self) -> None:
        if self._abort is not None:
            raise HomingFailed(Alarm.HOMING_RESET, self._abort)

    def status(self) -> dict[str, Any]:
        return {"homing": self.homing, "homed": sorted(self.homed),
                "triggered": [axis.switch for axis in self.triggered()]}


def grbl_settings(ctx: ModuleContext, config: EndstopsConfig, axes: list[_Axis]) -> None:
    """Grbl's homing settings on this module's config: ``$23`` the axes homing towards minus
    (a bit per axis, X first), ``$24`` the locate feed and ``$25`` the seek rate in mm/min,
    ``$26`` the debounce in ms, ``$27`` the pull-off in mm; each written to every axis, read
    as the slowest or smallest."""
    cfgs = [axis.cfg for axis in axes]

    def mask() -> float:
        return float(sum(1 << axis.index for axis in axes if axis.cfg.direction == "min"))

    def set_mask(value: float) -> None:
        for axis in axes:
            axis.cfg.direction = "min" if int(value) >> axis.index & 1 else "max"

    def each(key: str, scale: float) -> tuple[Callable[[], float], Callable[[float], None]]:
        def read() -> float:
            return float(min(getattr(cfg, key) for cfg in cfgs)) * scale

        def write(value: float) -> None:
            for cfg in cfgs:
                setattr(cfg, key, value / scale)
        return read, write

    def set_debounce(value: float) -> None:
        config.debounce_s = int(value) / 1000.0

    ctx.register_setting(23, "homing direction invert mask", mask, set_mask, high=255)
    ctx.register_setting(24, "homing locate feed, mm/min", *each("feed_mm_s", 60.0), high=1e6)
    ctx.register_setting(25, "homing seek rate, mm/min", *each("seek_mm_s", 60.0), high=1e6)
    ctx.register_setting(26, "homing debounce, ms", lambda: round(config.debounce_s * 1000.0),
                         set_debounce, high=5000)
    ctx.register_setting(27, "homing pull-off, mm", *each("pull_off_mm", 1.0), high=100)
