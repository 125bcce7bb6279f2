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
  laser off unless ``[jobs] frame_power_s`` is set, at ``[jobs] frame_feed_mm_min``. It answers
  when the frame has been traced, or when a hold, a reset or a halt ended it: a hold ends the
  frame once its deceleration is over (the rest is dropped, the laser off, the machine Idle),
  and the answer says ``stopped`` and why (``reason``: hold, reset, halt or the refusal).
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field

from server.api.jobs import NameParams
from server.api.methods import Methods, MethodTable, Params
from server.errors import CommandError, Error
from server.motion.motion_state import HoldState
from server.offline.fit import frame_lines
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    from collections.abc import Awaitable

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
            "estimate_s": None if plan.duration_s is None else round(plan.duration_s, 1),
            **_placement(m)}


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
    sent, reason = await _trace(m, connection, lines)
    return {"name": params.name, "lines": lines[:sent], "stopped": reason is not None,
            "reason": reason, **plan.fit.as_dict(kernel.config.core.axis_names)}


async def _trace(m: Methods, connection: Connection, lines: list[str]) -> tuple[int, str | None]:
    """Send the frame's lines and wait for its motion to end: (lines sent, why it stopped).
    A line may wait for planner room (long sides at a low feed): a hold ends that wait too."""
    reasons: list[str] = []
    ended = asyncio.Event()

    def stop(reason: str) -> None:
        reasons.append(reason)
        ended.set()

    events = m.kernel.events
    unsubscribe = [events.subscribe(event, lambda *_, r=reason: stop(r)) for event, reason in
                   ((Event.HOLD, "hold"), (Event.RESET, "reset"), (Event.HALT, "halt"))]
    sending = asyncio.ensure_future(_send(m, connection, lines, reasons))
    try:
        await _first(asyncio.shield(sending), ended.wait())
        if not reasons:  # every line is queued: until the motion ends
            await _first(m.machine.wait_idle(), ended.wait())
        if reasons and reasons[0] == "hold":
            await _end_held(m)  # (a line waiting for room is refused now)
        sent = await sending
    finally:
        sending.cancel()
        for cancel in unsubscribe:
            cancel()
    return sent, reasons[0] if reasons else None


async def _send(m: Methods, connection: Connection, lines: list[str],
                reasons: list[str]) -> int:
    """The frame's lines through the ordered path until one is refused or a stop came."""
    sent = 0
    for line in lines:
        if reasons:
            break
        try:
            await m.submit(connection, line)
        except CommandError as exc:  # a stop came, or the machine is locked
            reasons.append(f"error:{int(exc.code)} {exc.message}")
            break
        sent += 1
    return sent


async def _end_held(m: Methods) -> None:
    """A hold ended the frame: once its deceleration is over, the rest is dropped."""
    machine = m.machine
    if machine.stepgen.state.hold is HoldState.DECELERATING:
        stopped = asyncio.Event()
        cancel = m.kernel.events.subscribe(Event.HOLD_STOPPED, lambda: stopped.set())
        try:
            await _first(stopped.wait(), machine.wait_idle())  # (a reset: idle at once)
        finally:
            cancel()
    if m.kernel.state is MachineState.HOLD:
        machine.quickstop("frame held")


async def _first(*waits: Awaitable[Any]) -> None:
    """Until the first of ``waits`` is done; the others are cancelled."""
    tasks = [asyncio.ensure_future(wait) for wait in waits]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()


def _refuse_if_running(m: Methods) -> None:
    kernel = m.kernel
    if kernel.state is not MachineState.IDLE or kernel.jobs.active or m.machine.busy:
        raise CommandError(Error.BUSY, "cannot frame while the machine runs or a job is active")
