"""Builds the status snapshot that ``?``, the web UI and telemetry report."""

from __future__ import annotations

from typing import TYPE_CHECKING

from server.motion.moves import ToolMode
from server.motion.stepgen import HoldState, MotionState
from server.protocol.reports import StatusSnapshot
from server.runtime.events import MachineState

if TYPE_CHECKING:
    from server.runtime.kernel import Kernel


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
    """The machine as a status report shows it, now."""
    machine = kernel.machine
    downstream = machine.status_snapshot(rx_free_bytes)
    if downstream is not None:
        return downstream
    motion = machine.stepgen.state
    tool = machine.tool
    accessories = {ToolMode.CW: "S", ToolMode.CCW: "C"}.get(tool.mode, "")
    accessories += "F" * tool.flood + "M" * tool.mist
    pins = "".join(module.report_pins() for module in kernel.modules.values())
    return StatusSnapshot(
        state=state_text(kernel),
        machine_mm=motion.position_mm,
        wco_mm=machine.interpreter.wco(),
        feed_mm_s=motion.speed_mm_s,
        spindle_s=_spindle_s(motion.s_value if motion.moving else tool.s, tool.mode, motion),
        planner_free_blocks=max(0, machine.core.planner.max_blocks - len(machine.planner)),
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
