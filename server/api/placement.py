"""The JSON API's placement methods: where a job goes on the machine, and its frame.

Every one of them is G-code through the same ordered path as every line a sender sends
(:meth:`Methods.submit`), so it waits its turn, is refused while another source's motion or a
job runs (45), is locked out in ALARM, and a read-only connection cannot call it (46):

* ``machine.set_zero``: ``G10 L20 P0`` on the chosen axes (the active work coordinate system
  reads 0 where the tool is);
* ``machine.go_to_zero``: a jog (``$J=G90``) to work zero on the chosen axes;
* ``machine.wcs``: select G54-G59;
* ``job.place``: the job's extent under the current placement and whether it fits;
* ``job.frame``: trace that extent's rectangle (:func:`server.offline.fit.frame_lines`),
  laser off unless ``[jobs] frame_power_s`` is set, at ``[jobs] frame_feed_mm_min``. A hold or a
  reset during the frame stops it like any motion, and the lines not yet sent are dropped.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field

from server.api.jobs import NameParams
from server.api.methods import Methods, MethodTable, Params
from server.errors import CommandError, Error
from server.offline.fit import frame_lines
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    from server.api.server import Connection

PLACEMENT_METHODS = MethodTable()
method = PLACEMENT_METHODS.method
AXES = r"^[XYZABCxyzabc]*$"


class ZeroParams(Params):
    axes: str = Field("", pattern=AXES, description="axes to zero; empty: every axis")


class GoParams(Params):
    axes: str = Field("XY", pattern=AXES)
    feed_mm_min: float | None = Field(None, gt=0)


class WcsParams(Params):
    wcs: Literal["G54", "G55", "G56", "G57", "G58", "G59"]


def _axes(m: Methods, axes: str) -> list[str]:
    names = m.kernel.config.core.axis_names
    chosen = [a for a in names if a in axes.upper()] if axes else list(names)
    unknown = set(axes.upper()) - set(names)
    if unknown:
        raise CommandError(Error.UNUSED_AXIS_WORDS, f"no axis {''.join(sorted(unknown))}")
    return chosen


def _placement(m: Methods) -> dict[str, Any]:
    interpreter = m.machine.interpreter
    names = m.kernel.config.core.axis_names
    return {
        "wcs": interpreter.modal_snapshot()["wcs"],
        "wco_mm": dict(zip(names, (round(v, 4) for v in interpreter.wco()), strict=True)),
    }


@method("machine.set_zero", ZeroParams, control=True)
async def set_zero(m: Methods, connection: Connection, params: ZeroParams) -> dict[str, Any]:
    words = " ".join(f"{axis}0" for axis in _axes(m, params.axes))
    await m.submit(connection, f"G10 L20 P0 {words}")
    return _placement(m)


@method("machine.go_to_zero", GoParams, control=True)
async def go_to_zero(m: Methods, connection: Connection, params: GoParams) -> dict[str, Any]:
    axes = _axes(m, params.axes)
    core = m.kernel.config.core
    feed = params.feed_mm_min or min(core.axes[a.lower()].max_rate_mm_s for a in axes) * 60
    words = " ".join(f"{axis}0" for axis in axes)
    await m.submit(connection, f"$J=G21 G90 {words} F{feed:g}")
    return m.state()


@method("machine.wcs", WcsParams, control=True)
async def select_wcs(m: Methods, connection: Connection, params: WcsParams) -> dict[str, Any]:
    await m.submit(connection, params.wcs)
    return _placement(m)


@method("job.place", NameParams)
async def job_place(m: Methods, connection: Connection, params: NameParams) -> dict[str, Any]:
    """The job's extent (machine mm) under the current placement, against the travel."""
    plan = await m.kernel.jobs.plan(params.name)
    core = m.kernel.config.core
    travel = {name: [axis.min_mm, axis.max_mm]
              for name, axis in zip(core.axis_names, core.axes.values(), strict=True)}
    return {"name": params.name, **plan.fit.as_dict(core.axis_names), "travel_mm": travel,
            "estimate_s": round(plan.duration_s, 1), **_placement(m)}


@method("job.frame", NameParams, control=True)
async def job_frame(m: Methods, connection: Connection, params: NameParams) -> dict[str, Any]:
    kernel = m.kernel
    _refuse_if_running(m)
    plan = await kernel.jobs.plan(params.name)
    if not plan.fit.fits:
        raise CommandError(Error.JOB_DOES_NOT_FIT, f"{params.name}: {plan.fit.describe()}")
    _refuse_if_running(m)  # the plan took a while: check again
    jobs = kernel.config.core.jobs
    lines = frame_lines(plan.fit, jobs.frame_feed_mm_min, jobs.frame_power_s)
    stopped: list[str] = []
    events = kernel.events
    unsubscribe = [events.subscribe(event, lambda *_, e=event: stopped.append(e))
                   for event in (Event.HOLD, Event.RESET, Event.HALT)]
    sent = 0
    try:
        for line in lines:
            if stopped:
                break
            await m.submit(connection, line)
            sent += 1
    finally:
        for cancel in unsubscribe:
            cancel()
    return {"name": params.name, "lines": lines[:sent], "stopped": bool(stopped),
            **plan.fit.as_dict(kernel.config.core.axis_names)}


def _refuse_if_running(m: Methods) -> None:
    kernel = m.kernel
    if kernel.state is not MachineState.IDLE or kernel.jobs.active or m.machine.busy:
        raise CommandError(Error.BUSY, "cannot frame while the machine runs or a job is active")
