"""``[spindle]``: a PWM spindle driven by M3/M4/M5 and S, in order with motion (Grbl 1.1).

The interpreter turns every M3/M4/M5 and S change into an ordered ``spindle`` action; this
module applies it when the kernel's ``action`` event delivers it, that is when motion reaches
it. S is in RPM, multiplied by the spindle override, and mapped as Grbl does: S0 is off, up to
``min_rpm`` gives ``min_pwm``, ``max_rpm`` and above give ``max_pwm``, linear in between.
``dir_pin`` (optional) is 1 for M4.

The spindle goes off at once on halt (M112, alarm), soft reset (Ctrl-X) and shutdown. Like Grbl
it keeps
turning through a feed hold unless the spindle-stop realtime byte (0x9E) is sent during the
hold; it then restarts on resume.

``spin_up_delay_s``: when an M3/M4 starts the spindle from off, the interpreter queues a lead
dwell right after the spindle action (grblHAL's ``$340``), so motion waits for the spindle,
also when the same line moves (``G1 X10 M3 S12000`` spins up, waits, then moves).

A machine may configure both ``[laser]`` and ``[spindle]`` (a laser head on a CNC): both then
follow M3/M4/M5 and S, each on its own output; normally configure only the tool you have.

    [spindle]
    pin = "spindle"
    max_rpm = 24000
    min_rpm = 6000
    min_pwm = 0.1
    spin_up_delay_s = 3
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, model_validator

from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.motion.moves import Action, ActionName, ToolMode
from server.runtime.events import Event, MachineState

PIN_PATTERN = r"^[A-Za-z0-9_.\-]+$"


class SpindleConfig(ModuleConfig):
    pin: str = Field("spindle", pattern=PIN_PATTERN, description="PWM output name")
    dir_pin: str | None = Field(None, pattern=PIN_PATTERN, description="1 for M4 (CCW)")
    min_rpm: float = Field(0.0, ge=0, description="Grbl $31")
    max_rpm: float = Field(1000.0, gt=0, description="Grbl $30")
    min_pwm: float = Field(0.0, ge=0, le=1)
    max_pwm: float = Field(1.0, gt=0, le=1)
    spin_up_delay_s: float = Field(0.0, ge=0, le=60)

    @model_validator(mode="after")
    def _consistent(self) -> SpindleConfig:
        if self.min_rpm >= self.max_rpm:
            raise ValueError("min_rpm must be less than max_rpm")
        if self.min_pwm > self.max_pwm:
            raise ValueError("min_pwm must not exceed max_pwm")
        if self.dir_pin == self.pin:
            raise ValueError("dir_pin must differ from pin")
        return self


def spindle_pwm(config: SpindleConfig, mode: ToolMode, rpm: float) -> float:
    """Grbl's RPM -> PWM map (``spindle_compute_pwm_value``)."""
    if mode is ToolMode.OFF or rpm <= 0.0:
        return 0.0
    if rpm >= config.max_rpm:
        return config.max_pwm
    if rpm <= config.min_rpm:
        return config.min_pwm
    fraction = (rpm - config.min_rpm) / (config.max_rpm - config.min_rpm)
    return config.min_pwm + (config.max_pwm - config.min_pwm) * fraction


class Spindle(Module):
    """Applies spindle actions to a PWM output; see the module docstring."""

    name = "spindle"
    Config = SpindleConfig

    def __init__(self, ctx: ModuleContext, config: SpindleConfig) -> None:
        super().__init__(ctx, config)
        self.config: SpindleConfig = config
        self.mode = ToolMode.OFF
        self.rpm = 0.0
        self.pwm = 0.0
        self.override_percent = 100.0
        self.stopped_in_hold = False
        self._state = MachineState.IDLE
        ctx.outputs.declare_tool(config.pin)
        ctx.subscribe(Event.ACTION, self._on_action)
        ctx.subscribe(Event.OVERRIDE, self._on_override)
        ctx.subscribe(Event.HALT, self._halt)
        ctx.subscribe(Event.SHUTDOWN, self._halt)
        ctx.subscribe(Event.RESET, self._halt)
        ctx.subscribe(Event.STATE, self._on_state)
        ctx.subscribe(Event.SPINDLE_STOP, self._spindle_stop)
        ctx.subscribe(Event.RESUME, self._resume)
        if config.spin_up_delay_s > 0:
            ctx.set_spin_up_delay(config.spin_up_delay_s)

    # -- ordered actions -------------------------------------------------------------------
    def _on_action(self, action: Action) -> None:
        if action.name == ActionName.SPINDLE:
            self.mode = ToolMode(action.params["mode"])
            self.rpm = float(action.params["s"])
            self._output()

    def _on_override(self, feed: int, rapid: int, spindle: int) -> None:
        self.override_percent = float(spindle)
        self._output()

    def _output(self) -> None:
        on = not self.stopped_in_hold
        rpm = self.rpm * self.override_percent / 100.0
        self._set(spindle_pwm(self.config, self.mode, rpm) if on else 0.0)

    def _set(self, pwm: float) -> None:
        outputs = self.ctx.outputs
        if pwm != self.pwm:
            outputs.set(self.config.pin, pwm)
            self.pwm = pwm
        if self.config.dir_pin is not None:
            outputs.set(self.config.dir_pin, float(self.mode is ToolMode.CCW))

    # -- safety ----------------------------------------------------------------------------
    def _halt(self, *_: Any) -> None:
        self.mode, self.rpm, self.stopped_in_hold = ToolMode.OFF, 0.0, False
        self._set(0.0)

    def _on_state(self, state: MachineState) -> None:
        self._state = state
        if state is MachineState.ALARM:
            self._halt()

    def _spindle_stop(self) -> None:
        """Grbl's spindle stop override: toggles the spindle, only during a feed hold."""
        if self._state is MachineState.HOLD and self.mode is not ToolMode.OFF:
            self.stopped_in_hold = not self.stopped_in_hold
            self._output()

    def _resume(self) -> None:
        if self.stopped_in_hold:
            self.stopped_in_hold = False
            self._output()

    def status(self) -> dict[str, Any]:
        direction = {ToolMode.CW: "cw", ToolMode.CCW: "ccw"}.get(self.mode, "off")
        return {"direction": direction, "rpm": self.rpm, "pwm": self.pwm,
                "on": direction != "off", "max_rpm": self.config.max_rpm,
                "override": self.override_percent, "stopped_in_hold": self.stopped_in_hold}

