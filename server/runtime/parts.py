"""The machine's parts from its config: the backend, the interpreter's and the planner's
settings."""

from __future__ import annotations

from server.backends.base import Backend
from server.backends.null import NullBackend
from server.backends.sim import SimBackend
from server.config import CoreConfig
from server.gcode.interpreter import InterpreterSettings
from server.motion.planner import PlannerSettings


def build_backend(core: CoreConfig) -> Backend:
    """The backend named by ``[backend] kind``."""
    if core.backend.kind in ("null", "grbl"):  # a Grbl controller steps itself
        return NullBackend()
    if core.backend.kind == "klipper":
        from server.backends.klipper.backend import KlipperBackend  # only when configured

        return KlipperBackend(core)
    return SimBackend(
        core.axis_names,
        [axis.steps_per_mm for axis in core.axes.values()],
        history_samples=core.backend.history_samples,
        trace_csv=core.backend.trace_csv,
        probe_at_mm=core.backend.probe_at_mm,
    )


def interpreter_settings(core: CoreConfig, spin_up_delay_s: float = 0.0) -> InterpreterSettings:
    axes = list(core.axes.values())
    return InterpreterSettings(
        axis_names=core.axis_names,
        min_mm=tuple(axis.min_mm for axis in axes),
        max_mm=tuple(axis.max_mm for axis in axes),
        soft_limits=core.machine.soft_limits,
        arc_tolerance_mm=core.planner.arc_tolerance_mm,
        spin_up_delay_s=spin_up_delay_s,
    )


def planner_settings(core: CoreConfig) -> PlannerSettings:
    """Planner settings from the ``[axes.*]`` and ``[planner]`` sections."""
    axes = list(core.axes.values())
    planner = core.planner
    return PlannerSettings(
        max_rate_mm_s=tuple(axis.max_rate_mm_s for axis in axes),
        accel_mm_s2=tuple(axis.accel_mm_s2 for axis in axes),
        junction_deviation_mm=planner.junction_deviation_mm,
        max_blocks=planner.max_blocks,
        max_planned_s=planner.max_planned_s,
        min_feed_mm_s=planner.min_feed_mm_s,
    )
