"""The laser and the switches as Klipper's ``output_pin`` objects (pure).

Klipper's front-ends show an ``output_pin NAME`` object's ``value`` (0..1) and switch it with
``SET_PIN PIN=NAME VALUE=v``. motiond's outputs appear so:

- ``output_pin laser``: the laser's duty now (what the output does, as the backend times it),
  read-only: the power follows the G-code (``M3``/``M4 S..``) in order with motion, so a
  ``SET_PIN`` of it is refused;
- ``output_pin NAME`` for each ``[switch.NAME]`` (air assist, fan, light): its value; a
  ``SET_PIN`` becomes the switch's own line (``M8``/``M9``, ``M106 S..``, ``M42``), which runs
  through the ordered path of every sender.
"""

from __future__ import annotations

from typing import Any

from server.errors import CommandError, Error

LASER = "laser"
SWITCH_PREFIX = "switch."


def _switches(status: dict[str, Any]) -> dict[str, dict[str, Any]]:
    modules = status.get("modules", {})
    return {name[len(SWITCH_PREFIX):]: body for name, body in modules.items()
            if name.startswith(SWITCH_PREFIX)}


def output_pins(status: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``{"output_pin NAME": {"value": v}}`` for the laser and every switch."""
    pins: dict[str, dict[str, Any]] = {}
    laser = status.get("modules", {}).get(LASER)
    if laser is not None:
        pins[f"output_pin {LASER}"] = {"value": round(float(laser.get("power", 0.0)), 4)}
    for name, switch in _switches(status).items():
        pins[f"output_pin {name}"] = {"value": round(float(switch.get("value", 0.0)), 4)}
    return pins


def output_pin_settings(status: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``configfile.settings`` sections of the pins: ``pwm`` decides a slider or a toggle."""
    settings: dict[str, dict[str, Any]] = {}
    if LASER in status.get("modules", {}):
        settings[f"output_pin {LASER}"] = {"pin": LASER, "pwm": True, "scale": 1.0,
                                           "value": 0.0, "shutdown_value": 0.0}
    for name, switch in _switches(status).items():
        settings[f"output_pin {name}"] = {
            "pin": switch.get("pin", name), "pwm": switch.get("level_gcode") is not None,
            "scale": 1.0, "value": 0.0, "shutdown_value": 0.0}
    return settings


def set_pin_line(status: dict[str, Any], pin: str, value: float) -> str:
    """The motiond line that sets output ``pin`` to ``value`` (0..1), as ``SET_PIN`` asks;
    :class:`CommandError` in Klipper's words for the laser, an unknown pin or a bad value."""
    if pin == LASER and LASER in status.get("modules", {}):
        raise CommandError(Error.UNSUPPORTED, "SET_PIN: the laser's power follows the G-code "
                           "in order with motion (M3/M4 S.., M5): read-only here")
    switch = _switches(status).get(pin)
    if switch is None:
        raise CommandError(Error.UNSUPPORTED, f'SET_PIN: Pin "{pin}" not configured')
    if not 0.0 <= value <= 1.0:
        raise CommandError(Error.UNSUPPORTED, f"SET_PIN: VALUE must be between 0 and 1, "
                           f"not {value:g}")
    if value == 0.0:
        return str(switch["off_gcode"])
    level = switch.get("level_gcode")
    if level is None:
        return str(switch["on_gcode"])
    return f"{level}{value * float(switch.get('max_s', 255.0)):g}"
