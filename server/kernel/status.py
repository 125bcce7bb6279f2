"""Builds the status snapshots: the Grbl report (``?``) and the JSON status of the web UI.

:func:`build_status` is the one JSON status: the JSON API, its pushed updates and modules
(``ModuleContext.status()``, for example ``[mqtt]``) all read it, so every client sees the
same machine.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

from server.errors import ALARM_MEANINGS
from server.machine.parts import on_step_grid
from server.motion.motion_state import HoldState, MotionState
from server.motion.moves import MoveKind, ToolMode
from server.protocol.reports import StatusSnapshot, sender_blocks
from server.runtime.events import MachineState

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

CUTTING = frozenset({MoveKind.FEED, MoveKind.ARC, MoveKind.PROBE})


def state_text(kernel: Kernel) -> str:
    """Grbl's state field: ``Idle``, ``Run``, ``Hold:0``/``Hold:1``, ``Door:0``, ``Alarm``..."""
    state = kernel.state
    if state is MachineState.HOLD:
        decelerating = kernel.machine.stepgen.state.hold is HoldState.DECELERATING
        return "Hold:1" if decelerating else "Hold:0"
    if state is MachineState.DOOR:
        return "Door:0"
    return str(state.value)


def snapshot(kernel: Kernel, rx_free_bytes: int) -> StatusSnapshot:
    """The machine as a status report shows it, now: what the outputs do (in a hold in laser
    mode the laser is off: ``FS:..,0`` and no ``A:S``/``A:C``, as Grbl reports it)."""
    machine = kernel.machine
    downstream = machine.status_snapshot(rx_free_bytes)
    if downstream is not None:
        return downstream
    motion = machine.stepgen.state
    tool = machine.tool
    laser_held = kernel.state is MachineState.HOLD and machine.core.machine.laser_mode
    accessories = "" if laser_held else {ToolMode.CW: "S", ToolMode.CCW: "C"}.get(tool.mode, "")
    accessories += "F" * tool.flood + "M" * tool.mist
    pins = "".join(module.report_pins() for module in kernel.modules.values())
    capacity = machine.core.planner.max_blocks
    return StatusSnapshot(
        state=state_text(kernel),
        machine_mm=on_step_grid(machine.position_now_mm(), machine.core),
        wco_mm=machine.interpreter.wco(),
        feed_mm_s=machine.speed_now_mm_s(),
        spindle_s=0.0 if laser_held else _spindle_s(
            motion.s_value if motion.moving else tool.s, tool.mode, motion),
        planner_free_blocks=sender_blocks(capacity - len(machine.planner), capacity),
        rx_free_bytes=rx_free_bytes,
        line_number=motion.line_number if motion.moving else None,
        pins="".join(sorted(set(pins), key="PXYZABCDHRS".find)),
        overrides=(machine.feed_override, machine.rapid_override, machine.spindle_override),
        accessories=accessories,
    )


def _spindle_s(s_value: float, mode: ToolMode, motion: MotionState) -> float:
    """The S a status report shows: 0 once the spindle or laser is off, as Grbl does."""
    active = motion.tool_mode if motion.moving else mode
    return 0.0 if active is ToolMode.OFF else s_value


def build_status(kernel: Kernel) -> dict[str, Any]:
    """The machine as the web UI shows it: JSON-able, rounded so that noise is not a change."""
    machine = kernel.machine
    motion = machine.stepgen.state
    interpreter = machine.interpreter
    mpos = machine.position_now_mm()
    alarm = None
    if kernel.state is MachineState.ALARM:
        alarm = {
            "code": kernel.alarm_code,
            "message": kernel.alarm_message,
            "meaning": ALARM_MEANINGS.get(kernel.alarm_code, ""),
        }
    progress = kernel.jobs.progress()
    return {
        "state": state_text(kernel),
        "alarm": alarm,
        "mpos": _round(mpos),
        "wpos": _round(interpreter.work_position(mpos)),
        "wco": _round(interpreter.wco()),
        "speed_mm_min": round(machine.speed_now_mm_s() * 60.0, 1),
        "power_pct": round(tool_power_pct(kernel), 1),
        "tool": {
            "mode": f"M{int(machine.tool.mode)}",
            "s": machine.tool.s,
            "flood": machine.tool.flood,
            "mist": machine.tool.mist,
        },
        "moving": motion.moving,
        "queue_depth": len(machine.planner),
        "line": motion.line_number if motion.moving else None,
        "overrides": {
            "feed": machine.feed_override,
            "rapid": machine.rapid_override,
            "spindle": machine.spindle_override,
        },
        "modal": interpreter.modal_snapshot(),
        "job": None if progress is None else job_dict(progress),
        "modules": {name: module.status() for name, module in kernel.modules.items()},
        **{name: read() for name, read in kernel.status_fields.items()},
    }


def tool_power_pct(kernel: Kernel) -> float:
    """Tool power now, in percent: a module's ``power_pct`` status field when one gives it
    (the laser's real duty), else what Grbl's laser mode would fire (S over ``$30``, scaled
    by speed under M4)."""
    contributed = kernel.status_fields.get("power_pct")
    if contributed is not None:
        return float(contributed())
    motion = kernel.machine.stepgen.state
    if not motion.moving or motion.kind not in CUTTING or motion.tool_mode is ToolMode.OFF:
        return 0.0
    max_s = kernel.machine.settings.values().get(30, 1000.0) or 1000.0
    ratio = min(1.0, max(0.0, motion.s_value / max_s))
    if motion.tool_mode is ToolMode.CCW and motion.nominal_mm_s > 0:
        ratio *= min(1.0, motion.speed_mm_s / motion.nominal_mm_s)
    return 100.0 * ratio


def job_dict(progress: Any) -> dict[str, Any]:
    data = dataclasses.asdict(progress)
    for key in ("percent", "elapsed_s", "remaining_s", "estimate_s", "started_s"):
        if isinstance(data.get(key), float):
            data[key] = round(data[key], 1)
    return data


def _round(values: tuple[float, ...]) -> list[float]:
    return [round(value, 3) + 0.0 for value in values]
