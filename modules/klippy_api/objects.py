"""Klipper's printer objects, built from motiond's status snapshot (pure functions).

Every value comes from :func:`server.kernel.status.build_status` (what the machine executed:
``mpos`` is the step generator's or the board's position) and from the machine's config; no
extruder or heater is invented; the laser and the switches are output pins
(:mod:`modules.klippy_api.outputs`). Positions are Klipper's four-element lists
``[x, y, z, e]`` in mm, ``e`` always 0; speeds are mm/s (``gcode_move.speed`` mm/min, as
Klipper's). Soft-limit and other Grbl alarms keep ``webhooks.state`` ``ready`` (the front-end
stays usable, the message says what to do); an emergency stop (ALARM:40) and a failed module
or backend are ``shutdown``, which the front-ends show as such.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from modules.klippy_api import outputs
from server.errors import Alarm

SHUTDOWN_ALARMS = frozenset({Alarm.HALT, Alarm.MODULE_FAILED, Alarm.BACKEND_FAILED})
PRINT_STATES = {"running": "printing", "paused": "paused", "done": "complete",
                "aborted": "cancelled", "failed": "error"}
# Klipper's job macros, built in here: objects of their own, as the front-ends look for them.
MACROS = ("PAUSE", "RESUME", "CANCEL_PRINT")
OBJECT_NAMES = ("webhooks", "configfile", "gcode", "toolhead", "gcode_move", "motion_report",
                "print_stats", "virtual_sdcard", "pause_resume", "display_status",
                "idle_timeout", "system_stats", *(f"gcode_macro {name}" for name in MACROS))


@dataclass(frozen=True, slots=True)
class Machine:
    """What does not change: axis travel (mm), limits (mm/s, mm/s²), the jobs folder."""

    axis_min_mm: tuple[float, float, float]
    axis_max_mm: tuple[float, float, float]
    max_velocity_mm_s: float
    max_accel_mm_s2: float
    jobs_dir: Path
    homeable: frozenset[str]  # axes with a homing switch (lower case); the rest need none
    commands: dict[str, str] = field(default_factory=dict)  # G-code name -> help
    axes: str = "xyz"  # the machine's axes among X, Y, Z (lower case): no Z on an XY laser


@dataclass(slots=True)
class JobTimes:
    """Klipper's job durations on the kernel clock (s): ``total`` since the start, ``print``
    without the pauses; fed with every job state change (:meth:`update`)."""

    key: tuple[str, float] | None = None
    started_s: float = 0.0
    paused_s: float = 0.0
    pause_began_s: float | None = None
    ended_s: float | None = None

    def update(self, name: str, started_s: float, state: str, now_s: float) -> None:
        if self.key != (name, started_s):
            self.key, self.started_s, self.paused_s = (name, started_s), started_s, 0.0
            self.pause_began_s = self.ended_s = None
        if self.pause_began_s is not None and state != "paused":
            self.paused_s += now_s - self.pause_began_s
            self.pause_began_s = None
        if state == "paused" and self.pause_began_s is None:
            self.pause_began_s = now_s
        if state not in ("running", "paused") and self.ended_s is None:
            self.ended_s = now_s

    def durations(self, now_s: float) -> tuple[float, float]:
        """(total, printing) seconds, now, unrounded: as Klipper's, the total grows between
        any two updates of a job (Moonraker takes a ``printing`` whose total did not grow
        since ``paused`` for a new job, not a resume)."""
        end_s = now_s if self.ended_s is None else self.ended_s
        paused_s = self.paused_s + (0.0 if self.pause_began_s is None
                                    else end_s - self.pause_began_s)
        total_s = max(0.0, end_s - self.started_s)
        return total_s, max(0.0, total_s - paused_s)


@dataclass(slots=True)
class Extra:
    """State the status snapshot does not hold: M117's message, the job's file and times,
    the host."""

    message: str | None = None
    forgotten_job: tuple[str, float] | None = None  # (name, started_s) a restart ended
    file_size_bytes: int = 0
    host: dict[str, float] = field(default_factory=dict)  # sysload, cputime, memavail
    durations_s: tuple[float, float] = (0.0, 0.0)  # the job's (total, printing)


def build_objects(status: dict[str, Any], machine: Machine, extra: Extra) -> dict[str, Any]:
    """Every printer object, now (a job a restart ended is no job: ``standby``)."""
    job = status.get("job") or None
    if job is not None and (job.get("name"), job.get("started_s")) == extra.forgotten_job:
        job = None
    return {
        "webhooks": webhooks(status),
        "configfile": configfile(machine, outputs.output_pin_settings(status)),
        "gcode": {"commands": {name: {"help": text} for name, text in machine.commands.items()}},
        "toolhead": toolhead(status, machine),
        "gcode_move": gcode_move(status),
        "motion_report": motion_report(status),
        "print_stats": print_stats(job, extra.durations_s),
        "virtual_sdcard": virtual_sdcard(job, machine, extra),
        "pause_resume": {"is_paused": job is not None and job.get("state") == "paused"},
        "display_status": {"progress": _progress(job, extra.durations_s[1]),
                           "message": extra.message},
        "idle_timeout": idle_timeout(status, job),
        "system_stats": dict(extra.host),
        **{f"gcode_macro {name}": {} for name in MACROS},
        **outputs.output_pins(status),
    }


def webhooks(status: dict[str, Any]) -> dict[str, Any]:
    alarm = status.get("alarm")
    if alarm is None:
        return {"state": "ready", "state_message": "Printer is ready"}
    text = f"ALARM:{alarm['code']} {alarm['message']}".strip()
    if alarm.get("meaning"):
        text += f" ({alarm['meaning']})"
    if alarm["code"] in SHUTDOWN_ALARMS:
        return {"state": "shutdown", "state_message": f"{text}. FIRMWARE_RESTART or $X unlocks."}
    return {"state": "ready", "state_message": f"{text}. $X unlocks."}


def configfile(machine: Machine,
               pins: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """Klipper's raw config (strings) and settings (values) for what motiond has (``pins``:
    the output pins' sections, :mod:`modules.klippy_api.outputs`)."""
    settings: dict[str, dict[str, Any]] = {
        "printer": {"kinematics": "cartesian", "max_velocity": machine.max_velocity_mm_s,
                    "max_accel": machine.max_accel_mm_s2},
        "virtual_sdcard": {"path": str(machine.jobs_dir), "on_error_gcode": ""},
        "pause_resume": {"recover_velocity": 50.0},
        "display_status": {},
    }
    for name in (macro.lower() for macro in MACROS):  # built in: what the front-ends check
        settings[f"gcode_macro {name}"] = {"description": f"motiond: {name.upper()} is built in",
                                           "gcode": ""}
    for index, axis in enumerate("xyz"):
        if axis not in machine.axes:
            continue  # a front-end shows the axes whose stepper section exists
        settings[f"stepper_{axis}"] = {"position_min": machine.axis_min_mm[index],
                                       "position_max": machine.axis_max_mm[index]}
    settings.update(pins or {})
    config = {section: {key: str(value) for key, value in values.items()}
              for section, values in settings.items()}
    return {"config": config, "settings": settings, "save_config_pending": False,
            "save_config_pending_items": {}, "warnings": []}


def _xyze(values: list[float] | None) -> list[float]:
    values = list(values or [])[:3]
    return [*values, *[0.0] * (3 - len(values)), 0.0]


def homed_axes(status: dict[str, Any], machine: Machine) -> str:
    """Axes without a switch need no homing; the others once homed (``[endstops]``)."""
    homed = {name.lower() for name in status.get("modules", {}).get("endstops", {})
             .get("homed", [])}
    return "".join(axis for axis in machine.axes
                   if axis not in machine.homeable or axis in homed)


def toolhead(status: dict[str, Any], machine: Machine) -> dict[str, Any]:
    return {
        "homed_axes": homed_axes(status, machine),
        "axis_minimum": [*machine.axis_min_mm, 0.0],
        "axis_maximum": [*machine.axis_max_mm, 0.0],
        "position": _xyze(status.get("mpos")),
        "max_velocity": machine.max_velocity_mm_s,
        "max_accel": machine.max_accel_mm_s2,
        "minimum_cruise_ratio": 0.5,
        "square_corner_velocity": 5.0,
        "extruder": "",
        "print_time": 0.0,
        "estimated_print_time": 0.0,
        "stalls": 0,
    }


def gcode_move(status: dict[str, Any]) -> dict[str, Any]:
    modal = status.get("modal", {})
    return {
        "speed_factor": status.get("overrides", {}).get("feed", 100) / 100.0,
        "speed": float(modal.get("feed_mm_min") or 0.0),
        "extrude_factor": 1.0,
        "absolute_coordinates": modal.get("distance", "absolute") == "absolute",
        "absolute_extrude": True,
        "homing_origin": _xyze(status.get("wco")),
        "position": _xyze(status.get("mpos")),
        "gcode_position": _xyze(status.get("wpos")),
    }


def motion_report(status: dict[str, Any]) -> dict[str, Any]:
    return {
        "live_position": _xyze(status.get("mpos")),
        "live_velocity": round(float(status.get("speed_mm_min", 0.0)) / 60.0, 3),
        "live_extruder_velocity": 0.0,
        "steppers": [],
        "trapq": [],
    }


def print_stats(job: dict[str, Any] | None,
                durations_s: tuple[float, float] = (0.0, 0.0)) -> dict[str, Any]:
    if job is None:
        return {"filename": "", "total_duration": 0.0, "print_duration": 0.0,
                "filament_used": 0.0, "state": "standby", "message": "",
                "info": {"total_layer": None, "current_layer": None}}
    return {
        "filename": job["name"],
        "total_duration": durations_s[0],
        "print_duration": durations_s[1],
        "filament_used": 0.0,
        "state": PRINT_STATES.get(job["state"], "standby"),
        "message": job.get("error") or "",
        "info": {"total_layer": None, "current_layer": None},
    }


def _progress(job: dict[str, Any] | None, print_s: float = 0.0) -> float:
    """How far the job is, 0..1: by motiond's planned time where it has it, so that the
    front-ends' "time left" (print time / progress - print time) is motiond's remaining
    time; else by the lines run."""
    if job is None:
        return 0.0
    if job.get("state") == "done":
        return 1.0
    remaining_s = job.get("remaining_s")
    if remaining_s is not None and print_s + remaining_s > 0:
        return round(print_s / (print_s + float(remaining_s)), 4)
    done, total = job.get("lines_done", 0), job.get("lines_total", 0)
    return round(done / total, 4) if total else 0.0


def virtual_sdcard(job: dict[str, Any] | None, machine: Machine, extra: Extra) -> dict[str, Any]:
    """The job's file and how far it is, in bytes (``file_position``: the fraction done,
    :func:`_progress`, times the file's size)."""
    if job is None:
        return {"file_path": None, "progress": 0.0, "is_active": False, "file_position": 0,
                "file_size": 0}
    progress = _progress(job, extra.durations_s[1])
    return {
        "file_path": str(machine.jobs_dir / job["name"]),
        "progress": progress,
        "is_active": job["state"] == "running",
        "file_position": int(progress * extra.file_size_bytes),
        "file_size": extra.file_size_bytes,
    }


def idle_timeout(status: dict[str, Any], job: dict[str, Any] | None) -> dict[str, Any]:
    busy = bool(status.get("moving")) or (job is not None and job["state"] == "running")
    return {"state": "Printing" if busy else "Ready", "printing_time": 0.0}


def select(objects: dict[str, Any], wanted: dict[str, Any]) -> dict[str, Any]:
    """Klipper's ``objects/query`` answer: the asked fields (``None``: all) of each object;
    an unknown object answers ``{}``."""
    found: dict[str, Any] = {}
    for name, fields in wanted.items():
        values = objects.get(name, {})
        if isinstance(fields, list):
            values = {key: values[key] for key in fields if key in values}
        found[name] = values
    return found


def diff(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """The fields of ``new`` that differ from ``old`` (objects with no change left out)."""
    changed: dict[str, Any] = {}
    for name, values in new.items():
        before = old.get(name, {})
        fields = {key: value for key, value in values.items() if before.get(key) != value}
        if fields:
            changed[name] = fields
    return changed
