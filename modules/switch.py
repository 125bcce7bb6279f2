"""``[switch.NAME]``: a named output (fan, air assist, coolant, light) driven by M-codes.

Every switch command executes IN ORDER WITH MOTION: the switch claims ``on_mcode`` (M106 S...),
``off_mcode`` (M107) and ``M42 P<pin> S<value>`` with the interpreter, which turns them into an
``Action("switch")`` on the line they are on (``G1 X10 M106`` moves and switches); the output
changes when the kernel's ``action`` event delivers it, never when the line is received. The
value is ``S / max_s`` (S defaults to ``max_s``: full on), or 0/1 with ``pwm = false``.

M7, M8 and M9 belong to the interpreter, which turns them into a ``coolant`` action: a switch
with ``on_mcode = 7`` (mist) or ``8`` (flood) follows that action instead (M9 turns both off),
and Grbl's realtime coolant toggles (0xA0 flood, 0xA1 mist) switch it at once.
``M42 P<n>`` addresses the switch whose ``pin`` is ``n`` or ``P<n>``; a pin that no switch owns
is refused. Switches go off on shutdown, and at once on halt and soft reset (Ctrl-X) unless
``off_on_halt = false``.

    [switch.fan]
    pin = "fan"
    on_mcode = 106
    off_mcode = 107

    [switch.air]
    pin = "air"
    on_mcode = 8        # follows M8 / M9 (flood coolant)
    off_mcode = 9
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field, model_validator

from server.errors import CommandError, Error
from server.gcode.codes import CodeCall
from server.gcode.modal import M_GROUPS
from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.motion.moves import Action, ActionName, Output
from server.runtime.events import Event

PIN_PATTERN = r"^[A-Za-z0-9_.\-]+$"
COOLANT_CODES = {7: "mist", 8: "flood"}


class SwitchConfig(ModuleConfig):
    pin: str | None = Field(None, pattern=PIN_PATTERN,
                            description="output name (default: the switch's name)")
    on_mcode: int | None = Field(None, ge=0, le=999, description="M-code that turns it on")
    off_mcode: int | None = Field(None, ge=0, le=999, description="M-code that turns it off")
    max_s: float = Field(255.0, gt=0, description="S for full on (M106 S255)")
    pwm: bool = Field(True, description="S sets a duty cycle; false: any S > 0 is fully on")
    off_on_halt: bool = True

    @model_validator(mode="after")
    def _codes(self) -> SwitchConfig:
        on, off = self.on_mcode, self.off_mcode
        if on is not None and on == off:
            raise ValueError("on_mcode and off_mcode must differ")
        if on in COOLANT_CODES:
            if off not in (None, 9):
                raise ValueError(f"a coolant switch (on_mcode = {on}) turns off with M9")
        elif off == 9:
            raise ValueError("off_mcode = 9 needs on_mcode = 7 (mist) or 8 (flood)")
        for key, code in (("on_mcode", on), ("off_mcode", off)):
            if code is not None and code in M_GROUPS and code not in (7, 8, 9):
                raise ValueError(f"{key}: M{code} belongs to the G-code interpreter")
        return self


class Switch(Module):
    """One named output; see the module docstring."""

    name = "switch"
    Config = SwitchConfig
    named: ClassVar[bool] = True

    def __init__(self, ctx: ModuleContext, config: SwitchConfig) -> None:
        super().__init__(ctx, config)
        self.config: SwitchConfig = config
        self.pin = config.pin or ctx.name.split(".", 1)[-1]
        self.value = 0.0
        self.coolant = COOLANT_CODES.get(config.on_mcode or -1)
        if self.coolant is None:
            if config.on_mcode is not None:
                ctx.register_code(config.on_mcode, self._on_code)
            if config.off_mcode is not None:
                ctx.register_code(config.off_mcode, self._off_code)
        else:
            ctx.subscribe(Event.TOGGLE_COOLANT, self._toggle)
        ctx.register_code(42, self._m42, group="M42", uses="P", key=("P", self.pin))
        ctx.subscribe(Event.ACTION, self._on_action)
        if config.off_on_halt:
            ctx.subscribe(Event.HALT, self._off_now)
            ctx.subscribe(Event.RESET, self._off_now)
        ctx.subscribe(Event.SHUTDOWN, self._off_now)

    # -- codes: the interpreter queues the action, in order with motion ----------------------
    def _on_code(self, call: CodeCall) -> list[Output]:
        return [self._action(self._value_from_s(call.values.get("S")))]

    def _off_code(self, call: CodeCall) -> list[Output]:
        return [self._action(0.0)]

    def _m42(self, call: CodeCall) -> list[Output]:
        s = call.values.get("S")
        if s is None:
            raise CommandError(Error.VALUE_WORD_MISSING, "M42 needs P<pin> and S<value>")
        return [self._action(self._value_from_s(s))]

    def _value_from_s(self, s: float | None) -> float:
        if s is None:
            return 1.0
        value = min(1.0, s / self.config.max_s)  # the interpreter refuses a negative S
        return value if self.config.pwm else float(value > 0.0)

    def _action(self, value: float) -> Action:
        return Action("switch", {"section": self.ctx.name, "value": value})

    # -- applied when motion reaches the action ---------------------------------------------
    def _on_action(self, action: Action) -> None:
        params = action.params
        if action.name == "switch" and params.get("section") == self.ctx.name:
            self._set(float(params["value"]))
        elif action.name == ActionName.COOLANT and self.coolant is not None:
            self._set(1.0 if params.get(self.coolant) else 0.0)

    def _toggle(self, kind: str) -> None:
        """Grbl's realtime coolant override: toggles at once."""
        if kind == self.coolant:
            self._set(0.0 if self.value > 0.0 else 1.0)

    def _off_now(self, *_: Any) -> None:
        self._set(0.0)

    def _set(self, value: float) -> None:
        if value != self.value:
            self.ctx.outputs.set(self.pin, value)
            self.value = value

    def status(self) -> dict[str, Any]:
        """State, and the lines that switch it (for the UI's button): its M-codes, M9 for a
        coolant switch, else M42; ``level_gcode`` + ``S<value>`` sets a PWM switch's level."""
        on, off = self.config.on_mcode, self.config.off_mcode
        if off is None and self.coolant is not None:
            off = 9
        m42 = f"M42 P{self.pin} S"
        level = None  # a line that takes S<0..max_s> (a PWM switch), else only on and off
        if self.config.pwm and self.coolant is None:
            level = f"M{on} S" if on is not None else m42
        return {"pin": self.pin, "value": self.value, "on": self.value > 0.0,
                "on_gcode": f"M{on}" if on is not None else f"{m42}{self.config.max_s:g}",
                "off_gcode": f"M{off}" if off is not None else f"{m42}0",
                "level_gcode": level, "max_s": self.config.max_s}
