"""``[laser]``: a laser whose power follows the tool's speed (Grbl laser mode, Smoothie's laser).

A task samples the step generator's motion state on its own fixed-rate timer (``sample_hz``,
capped by ``pwm_frequency_hz``) and sets the PWM duty of ``pin`` on the backend. S and M3/M4/M5
come from the block being executed (``MotionState.s_value``/``tool_mode``), so S changes between
segments ride inside the blocks and never stop motion. Where the backend times its own steps
from the trajectory (a Klipper MCU) and no ``ttl_pin`` is set, it times the PWM too: each block's
power law (:func:`power_law`) rides on its pieces, and the board changes the duty on the very
steps it belongs to, at most every sample period along an acceleration; the sampler then only
ends a ``fire``.

Power while a G1/G2/G3 block executes (``r = S / maximum_s_value * scale``):

* dynamic (M4, and M3 with ``proportional_power``, as Smoothieware):
  ``min + (max - min) * r * speed / nominal``, so accelerations and decelerations are scaled;
* constant (M3, Grbl's ``$32`` laser mode): ``min + (max - min) * r``;

clamped to ``[0, maximum_power]``. Rapids, jogs and homing moves never fire; M5, S0 and a
machine at rest turn it off. ``scale`` is M221's percentage times the spindle override %.

``M221 S<percent>`` is an *ordered* action: it takes effect when motion reaches it, like S.
Halt, alarm, feed hold, sleep and shutdown turn the laser off at once, inside the event
callback; after a resume it comes back with the motion at the next sample. The sampled power
lags the motion state by at most one sample period (a real controller's PWM update lag).

Smoothie's ``fire <percent> [seconds]`` fires while idle (focusing); ``fire off`` stops it. It
is refused with ``error:45`` unless the machine is Idle and still, and ends by itself after
``fire_max_duration_s``, when the machine leaves Idle, or at the next sample after a Ctrl-X.

    [laser]
    pin = "laser"
    maximum_s_value = 1000      # LightBurn/Grbl files; Smoothie uses 1.0
    maximum_power = 0.8
    proportional_power = false  # M3 constant, M4 dynamic
    ttl_pin = "laser_enable"    # optional: 1 while firing
"""

from __future__ import annotations

import asyncio
from typing import Any

from pydantic import Field, model_validator

from server.errors import CommandError, Error
from server.gcode.codes import CodeCall
from server.kernel.module import ApiCaller, ApiParams, Module, ModuleConfig, ModuleContext
from server.motion.backend import PowerLaw
from server.motion.motion_state import HoldState, MotionState
from server.motion.moves import Action, Move, MoveKind, Output, Sync, SyncKind, ToolMode
from server.runtime.clock import VirtualClock
from server.runtime.dispatcher import Command
from server.runtime.events import Event, MachineState

PIN_PATTERN = r"^[A-Za-z0-9_.\-]+$"
CUTTING_KINDS = frozenset({MoveKind.FEED, MoveKind.ARC})
OFF_STATES = frozenset({MachineState.ALARM, MachineState.HOLD, MachineState.SLEEP,
                        MachineState.DOOR})
# States in which, with nothing moving and no fire, the power stays 0: the sampler rests.
RESTING_STATES = OFF_STATES | {MachineState.IDLE}


class LaserConfig(ModuleConfig):
    pin: str = Field("laser", pattern=PIN_PATTERN, description="PWM output name")
    ttl_pin: str | None = Field(None, pattern=PIN_PATTERN,
                                description="optional enable output, 1 while firing")
    pwm_frequency_hz: float = Field(5000.0, gt=0, le=1_000_000)
    sample_hz: float = Field(1000.0, ge=10, le=100_000,
                             description="power updates per second (capped by the PWM frequency)")
    maximum_power: float = Field(1.0, gt=0, le=1, description="duty at full power")
    minimum_power: float = Field(0.0, ge=0, le=1, description="duty at the lowest power")
    maximum_s_value: float = Field(1000.0, gt=0, description="S for full power (Grbl $30)")
    proportional_power: bool = Field(False, description="M3 scales with speed too (Smoothie)")
    fire_max_duration_s: float = Field(10.0, gt=0, le=3600)

    @model_validator(mode="after")
    def _consistent(self) -> LaserConfig:
        if self.minimum_power > self.maximum_power:
            raise ValueError("minimum_power must not exceed maximum_power")
        if self.ttl_pin == self.pin:
            raise ValueError("ttl_pin must differ from pin")
        return self

    @property
    def period_s(self) -> float:
        """Seconds between two power updates."""
        return 1.0 / min(self.sample_hz, self.pwm_frequency_hz)


def power_law(config: LaserConfig, kind: MoveKind | None, tool_mode: ToolMode, s_value: float,
              nominal_mm_s: float, scale: float) -> PowerLaw | None:
    """The duty as a function of the speed along a move (see the module docstring); None:
    the laser is off along it."""
    if kind not in CUTTING_KINDS or tool_mode is ToolMode.OFF or s_value <= 0.0:
        return None
    ratio = s_value / config.maximum_s_value * scale
    low, high = config.minimum_power, config.maximum_power
    if tool_mode is ToolMode.CCW or config.proportional_power:
        per_mm_s = (high - low) * ratio / nominal_mm_s if nominal_mm_s > 0.0 else 0.0
        return PowerLaw(low, per_mm_s, high)
    return PowerLaw(low + (high - low) * ratio, 0.0, high)


def laser_power(config: LaserConfig, motion: MotionState, scale: float) -> float:
    """The duty cycle in [0, maximum_power] for the motion state (see the module docstring)."""
    if not motion.moving or motion.hold is not HoldState.NONE:
        return 0.0
    law = power_law(config, motion.kind, motion.tool_mode, motion.s_value, motion.nominal_mm_s,
                    scale)
    return 0.0 if law is None else law.at(motion.speed_mm_s)


class FireParams(ApiParams):
    """``laser.fire``: power in percent, optional duration (capped by fire_max_duration_s)."""

    percent: float = Field(ge=0, le=100)
    duration_s: float | None = Field(None, gt=0)


class Laser(Module):
    """Drives the laser PWM from the motion state; see the module docstring."""

    name = "laser"
    Config = LaserConfig

    def __init__(self, ctx: ModuleContext, config: LaserConfig) -> None:
        super().__init__(ctx, config)
        self.config: LaserConfig = config
        self.power = 0.0
        self.m221_percent = 100.0
        self.override_percent = 100.0
        self._state = MachineState.IDLE
        self._fire_until_s: float | None = None
        self._law_key: tuple[object, ...] = ()  # what the last block's power law came from
        self._law: PowerLaw | None = None
        self._wake = asyncio.Event()  # a state change or a fire: the resting sampler resumes
        ctx.register_command("fire", self._fire)
        ctx.register_api_method("laser.fire", self._api_fire, FireParams, control=True)
        ctx.register_api_method("laser.off", self._api_off, control=True)
        ctx.add_status_field("power_pct", lambda: round(100.0 * self.output_power, 1))
        ctx.add_feature("laser")
        ctx.outputs.declare_tool(config.pin)
        # a backend that times the pin from the trajectory itself (a Klipper MCU) gets each
        # block's power law; the sampler then only ends a fire
        self.follows = config.ttl_pin is None and ctx.outputs.follow_motion(
            config.pin, self._power_of, config.period_s)
        ctx.register_code(221, self._m221, uses="S", query=True)
        for event in ("halt", "hold", "shutdown", "reset"):
            ctx.subscribe(event, self._off_now)
        ctx.subscribe(Event.STATE, self._on_state)
        ctx.subscribe(Event.OVERRIDE, self._on_override)
        ctx.subscribe(Event.ACTION, self._on_action)

    @property
    def scale(self) -> float:
        """M221 percentage times the spindle override percentage, as a factor."""
        return self.m221_percent / 100.0 * self.override_percent / 100.0

    @property
    def output_power(self) -> float:
        """The duty on the pin now (where the backend times it, the last it scheduled)."""
        return self.ctx.outputs.value(self.config.pin) if self.follows else self.power

    @property
    def firing(self) -> bool:
        """Whether a ``fire`` command holds the laser on."""
        return self._fire_until_s is not None

    async def run(self) -> None:
        """Sample the motion state at a fixed rate until cancelled; the laser ends off. While
        the machine rests (idle, nothing moving, no fire: the power can only be 0) the sampler
        waits for a state change or a fire instead (on real time: a virtual clock's time runs
        only as fast as its sleepers)."""
        clock = self.ctx.clock
        period_s = self.config.period_s
        next_s = clock.now_s()
        may_rest = not isinstance(clock, VirtualClock)  # as the step generator's tick
        try:
            while True:
                if may_rest and self._resting():
                    self._wake.clear()
                    await self._wake.wait()
                    next_s += (clock.now_s() - next_s) // period_s * period_s  # same phase
                next_s += period_s
                await clock.sleep_until(next_s)
                now_s = clock.now_s()
                if now_s - next_s > 0.25:  # the loop stalled: do not replay old samples
                    next_s = now_s
                self._sample(now_s)
        finally:
            self._off_now()

    def _resting(self) -> bool:
        if self.follows:
            return not self.firing
        return (self._state in RESTING_STATES and not self.firing and self.power == 0.0
                and not self.ctx.motion().moving)

    def _sample(self, now_s: float) -> None:
        if self._fire_until_s is not None:
            if now_s < self._fire_until_s:
                return
            self._fire_until_s = None  # expired (halt, hold and reset end it at once)
            self.ctx.log.info("fire: stopped")
        self._apply(0.0 if self.follows else laser_power(self.config, self.ctx.motion(),
                                                         self.scale))

    def _power_of(self, move: Move, nominal_mm_s: float) -> PowerLaw | None:
        """A block's power law; the last block's again (the same object) when nothing it
        depends on changed: a raster's blocks then continue one piece without comparing
        their laws field by field (:mod:`server.motion.pieces`)."""
        key = (move.kind, move.tool_mode, move.s_value, nominal_mm_s, self.m221_percent,
               self.override_percent)
        if key != self._law_key:
            self._law_key = key
            self._law = power_law(self.config, move.kind, move.tool_mode, move.s_value,
                                  nominal_mm_s, self.scale)
        return self._law

    def _apply(self, power: float) -> None:
        if power == self.power:
            return
        outputs = self.ctx.outputs
        outputs.set(self.config.pin, power)
        if self.config.ttl_pin is not None and (power > 0.0) != (self.power > 0.0):
            outputs.set(self.config.ttl_pin, 1.0 if power > 0.0 else 0.0)
        self.power = power

    # -- events (synchronous: the laser is off before emit() returns) ----------------------
    def _off_now(self, *_: Any) -> None:
        self._fire_until_s = None
        if self.follows:  # the backend may have it on from the trajectory
            self.ctx.outputs.set(self.config.pin, 0.0)
        self._apply(0.0)

    def _on_state(self, state: MachineState) -> None:
        self._state = state
        self._wake.set()
        if state in OFF_STATES:
            self._off_now()
        elif state is not MachineState.IDLE and self.firing:
            self._off_now()  # motion started: fire ends, the sampler takes over

    def _on_override(self, feed: int, rapid: int, spindle: int) -> None:
        self.override_percent = float(spindle)

    def _on_action(self, action: Action) -> None:
        if action.name == "laser" and "scale_percent" in action.params:
            self.m221_percent = float(action.params["scale_percent"])

    # -- commands --------------------------------------------------------------------------
    def _m221(self, call: CodeCall) -> list[Output]:
        """``M221 S<percent>``: power scale, applied in order with motion; bare M221 reports."""
        percent = call.values.get("S")
        if percent is None:
            report = f"[MSG:laser power scale {self.m221_percent:g}%]"
            return [Sync(SyncKind.MESSAGE, {"lines": [report]})]
        if not 0.0 <= percent <= 1000.0:
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, "M221 S must be a percentage between 0 and 1000"
            )
        return [Action("laser", {"scale_percent": percent})]

    def _fire(self, command: Command) -> list[str]:
        """``fire <percent> [seconds]`` while idle, ``fire off`` at any time."""
        args = command.args.split()
        if len(args) == 1 and args[0].lower() == "off":
            self._off_now()
            return ["[MSG:fire off]"]
        if not 1 <= len(args) <= 2:
            raise CommandError(
                Error.INVALID_STATEMENT, "usage: fire <percent> [seconds] | fire off"
            )
        try:
            percent, *rest = (float(arg) for arg in args)
        except ValueError as exc:
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, f"fire: not a number: {command.args!r}"
            ) from exc
        if not 0.0 <= percent <= 100.0:
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, "fire: the power is a percentage from 0 to 100"
            )
        motion = self.ctx.motion()
        if self._state is not MachineState.IDLE or motion.moving or motion.queue_depth:
            raise CommandError(Error.BUSY, "fire only works while the machine is idle")
        limit_s = self.config.fire_max_duration_s
        duration_s = min(rest[0], limit_s) if rest and rest[0] > 0 else limit_s
        now_s = self.ctx.clock.now_s()
        self._fire_until_s = now_s + duration_s
        self._apply(min(1.0, percent / 100.0) * self.config.maximum_power)
        self._wake.set()
        return [f"[MSG:fire {percent:g}% for at most {duration_s:g}s]"]

    async def _api_fire(self, params: FireParams, caller: ApiCaller) -> dict[str, Any]:
        """``laser.fire``: the ``fire`` command, as the calling connection."""
        duration = "" if params.duration_s is None else f" {params.duration_s:g}"
        return {"messages": await caller.submit(f"fire {params.percent:g}{duration}")}

    async def _api_off(self, params: ApiParams, caller: ApiCaller) -> dict[str, Any]:
        return {"messages": await caller.submit("fire off")}

    def status(self) -> dict[str, Any]:
        motion = self.ctx.motion()
        return {"power": self.output_power, "s": motion.s_value, "scale": self.scale,
                "firing": self.firing}
