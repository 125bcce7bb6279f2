"""What the Klipper backend configures on the MCU: axes, outputs, their pins and oids."""

from __future__ import annotations

from dataclasses import dataclass

from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.mcu import Command, KlipperFault
from server.backends.klipper.stepcore import StepAxis
from server.config import BackendConfig, KlipperOutput


def split_pin(text: str) -> tuple[str, bool]:
    """``"!PB4"`` -> ``("PB4", True)``."""
    return text.lstrip("!"), text.startswith("!")


class Axis:
    """One stepper: its oid, and its steps (the compiled :class:`StepAxis`: where they are,
    the steps held until they are due, compressed and encoded there too)."""

    __slots__ = ("name", "oid", "invert_dir", "steps", "enable_oid", "enable_inverted")

    def __init__(self, name: str, steps_per_mm: float, steps: StepAxis | None = None) -> None:
        self.name = name
        self.oid = 0
        self.invert_dir = False
        self.steps = StepAxis() if steps is None else steps
        self.steps.steps_per_mm = steps_per_mm
        self.enable_oid: int | None = None  # its enable pin's digital output, if it has one
        self.enable_inverted = False

    @property
    def position(self) -> int:
        """Whole steps commanded so far."""
        return self.steps.position

    @position.setter
    def position(self, steps: int) -> None:
        self.steps.position = steps

    @property
    def steps_per_mm(self) -> float:
        return self.steps.steps_per_mm

    @steps_per_mm.setter
    def steps_per_mm(self, value: float) -> None:
        self.steps.steps_per_mm = value

    def configure(self, oid: int, d: Dictionary, max_error_ticks: float) -> None:
        """What configuring the MCU sets: its oid, the compression's bound, the step
        commands' ids; the next steps start with a ``reset_step_clock``."""
        self.oid = oid
        self.steps.configure(oid, self.invert_dir, max_error_ticks, *d.step_prefixes())


@dataclass(slots=True)
class Output:
    """One output pin and the last value sent to it."""

    name: str
    config: KlipperOutput
    oid: int = 0
    invert: bool = False
    last_clock: int = 0
    value: float = 0.0  # the last value sent (0 after a configuration or a stop)
    max_ticks: int = 0  # the firmware's max_duration: on longer than this without a refresh
    # (a new event), the board shuts down and the output goes off


def config_commands(cfg: BackendConfig, axes: list[Axis], outputs: dict[str, Output],
                    d: Dictionary) -> list[Command]:
    """The MCU's configuration: a ``config_stepper`` (and enable pin) per axis, a
    ``config_pwm_out`` or ``config_digital_out`` per output with the firmware's watchdog
    (``max_duration``: off when motiond stops refreshing it); assigns the oids."""
    freq = d.constant_int("CLOCK_FREQ")
    commands: list[Command] = []
    oid = 0
    for axis, (name, pins) in zip(axes, cfg.axes.items(), strict=True):
        step, invert_step = split_pin(check_pin(d, f"axes.{name}", pins.step_pin))
        direction, axis.invert_dir = split_pin(check_pin(d, f"axes.{name}",
                                                               pins.dir_pin))
        axis.configure(oid, d, cfg.max_error_s * freq)
        commands.append(("config_stepper", {
            "oid": oid, "step_pin": step, "dir_pin": direction,
            "invert_step": int(invert_step),
            "step_pulse_ticks": int(pins.step_pulse_s * freq)}))
        oid += 1
        if pins.enable_pin:
            enable, inverted = split_pin(check_pin(d, f"axes.{name}", pins.enable_pin))
            axis.enable_oid, axis.enable_inverted = oid, inverted
            commands.append(("config_digital_out", {
                "oid": oid, "pin": enable, "value": int(not inverted),
                "default_value": int(inverted), "max_duration": 0}))
            oid += 1
    for name, out in outputs.items():
        pin_text = check_pin(d, f"outputs.{name}", out.config.pin or name)
        pin, out.invert = split_pin(pin_text)
        out.oid, oid = oid, oid + 1
        out.max_ticks = int(out.config.max_duration_s * freq)
        if out.config.pwm:
            off = d.constant_int("PWM_MAX", 255) if out.invert else 0
            commands.append(("config_pwm_out", {
                "oid": out.oid, "pin": pin, "cycle_ticks": int(out.config.cycle_time_s * freq),
                "value": off, "default_value": off, "max_duration": out.max_ticks}))
        else:
            commands.append(("config_digital_out", {
                "oid": out.oid, "pin": pin, "value": int(out.invert),
                "default_value": int(out.invert), "max_duration": out.max_ticks}))
    return commands

def check_pin(d: Dictionary, section: str, text: str) -> str:
    """``text`` if its pin is one the MCU's dictionary names, else a config error."""
    if split_pin(text)[0] not in d.enumerations.get("pin", {}):
        raise KlipperFault(f"config error: [backend.{section}]: unknown pin {text!r} on "
                           f"this MCU ({d.constants.get('MCU', '?')})")
    return text
