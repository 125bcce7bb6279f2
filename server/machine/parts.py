"""The machine's parts from its config: the interpreter's and the planner's settings (the
backend is built by :func:`server.backends.build.build_backend`)."""

from __future__ import annotations

from server.config import CoreConfig
from server.gcode.interpreter import InterpreterSettings
from server.motion.planner import PlannerSettings


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


def on_step_grid(position_mm: tuple[float, ...], core: CoreConfig) -> tuple[float, ...]:
    """A position as the steppers hold it: whole steps of each axis, as a board reports its
    step counts (``MPos``, ``[PRB:]``); the step generator's own position lies between steps."""
    return tuple(round(value * axis.steps_per_mm) / axis.steps_per_mm
                 for value, axis in zip(position_mm, core.axes.values(), strict=True))
