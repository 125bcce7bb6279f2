"""What the Klipper backend configures on the MCU: axes, outputs, their pins and oids."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.mcu import Command, KlipperFault
from server.backends.klipper.stepcompress import StepCompressor
from server.backends.klipper.steptimes import FloatArray
from server.config import BackendConfig, KlipperOutput


def split_pin(text: str) -> tuple[str, bool]:
    """``"!PB4"`` -> ``("PB4", True)``."""
    return text.lstrip("!"), text.startswith("!")


@dataclass(slots=True)
class Axis:
    """One stepper: its oid, where its steps are, and what waits to be compressed."""

    name: str
    steps_per_mm: float
    oid: int = 0
    invert_dir: bool = False
    position: int = 0  # whole steps commanded so far
    segments: list[tuple[int, FloatArray]] = field(default_factory=list)  # (dir, exact clocks)
    pending: list[FloatArray] = field(default_factory=list)  # added, not yet in segments
    pending_dir: int = 0
    compressor: StepCompressor = field(default_factory=lambda: StepCompressor(1.0))
    sent_dir: int = 0
    needs_reset: bool = True
    enable_oid: int | None = None  # its enable pin's digital output, if it has one
    enable_inverted: bool = False
    exact: list[FloatArray] | None = None  # recorded exact clocks (tests, benchmarks)

    def add(self, direction: int, clocks: FloatArray) -> None:
        if self.exact is not None:
            self.exact.append(clocks)
        if self.pending and self.pending_dir != direction:
            self.collect()
        self.pending.append(clocks)
        self.pending_dir = direction

    def holds(self, before_clock: float) -> bool:
        """Whether :meth:`collect` may wait: what was added runs one way, and its first step
        is not due before ``before_clock`` (a run still growing is not copied every flush)."""
        first = self.first_clock()
        return first is None or first >= before_clock

    def first_clock(self) -> float | None:
        """The clock from which what this axis holds must be looked at: its first step's, 0
        when at once (runs both ways wait), None when it holds nothing."""
        segments, pending = self.segments, self.pending
        if len(segments) > 1 or (segments and pending and self.pending_dir != segments[0][0]):
            return 0.0
        if segments:
            return float(segments[0][1][0])
        return float(pending[0][0]) if pending else None

    def collect(self) -> None:
        """The pieces' step clocks added since the last call join :attr:`segments` (at most
        one concatenation per flush, not one per piece)."""
        pending, segments, direction = self.pending, self.segments, self.pending_dir
        if not pending:
            return
        self.pending = []
        if segments and segments[-1][0] == direction:  # one copy: the held run and the new
            segments[-1] = (direction, np.concatenate((segments[-1][1], *pending)))
        else:
            segments.append((direction, pending[0] if len(pending) == 1
                             else np.concatenate(pending)))


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
        axis.oid, axis.compressor = oid, StepCompressor(cfg.max_error_s * freq)
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
