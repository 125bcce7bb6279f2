"""One client of Klipper's API socket (Moonraker): its requests, subscriptions and scripts.

Requests are answered at once, but ``gcode/script``: scripts run one after another in a task
of the session (:meth:`Session.run_scripts`), each line through ``ModuleContext.run_gcode``,
the ordered path of every sender, so a script waiting for planner room never delays a query,
a pause or an emergency stop. At most ``PENDING_SCRIPTS`` wait; more are refused. A script
holding only ``PAUSE``/``RESUME``/``CANCEL_PRINT``/``M112`` (and ``emergency_stop``,
``pause_resume/*``) acts on arrival, as the realtime bytes of a Grbl sender do.

The session never writes to a socket: :attr:`Session.send` takes each message (the transport
queues it, bounded).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from typing import Any, Protocol

from modules.klippy_api import gcode, objects, outputs, wire
from modules.klippy_api.gcode import (
    Control,
    FeedOverride,
    GcodeOffset,
    Line,
    Message,
    SetPin,
    StartJob,
    Step,
)
from server.errors import CommandError, Error
from server.kernel.control import halts_at_once
from server.kernel.module import ModuleContext

PENDING_SCRIPTS = 32
IMMEDIATE = frozenset({"pause", "resume", "cancel", "estop"})
ENDPOINTS = ("info", "list_endpoints", "objects/list", "objects/query", "objects/subscribe",
             "gcode/script", "gcode/help", "gcode/subscribe_output", "gcode/restart",
             "gcode/firmware_restart", "emergency_stop", "register_remote_method",
             "pause_resume/pause", "pause_resume/resume", "pause_resume/cancel")


class Hub(Protocol):
    """What a session needs of the module (shared by every session)."""

    ctx: ModuleContext
    jog_feed_mm_min: float
    job_state: str | None  # the last job's state (running, paused, done...), None before

    def objects(self) -> dict[str, Any]: ...

    def info(self) -> dict[str, Any]: ...

    def set_message(self, text: str | None) -> None: ...

    def output(self, text: str) -> None:
        """Send a G-code response line to every output subscriber."""
        ...

    def restart(self) -> None:
        """Close every API connection (after RESTART/FIRMWARE_RESTART)."""
        ...


class Session:
    """One connection's state: subscription, output subscription, queued scripts."""

    def __init__(self, hub: Hub, send: Callable[[dict[str, Any]], None]) -> None:
        self.hub, self.send = hub, send
        self.subscription: dict[str, list[str] | None] = {}
        self.status_template: dict[str, Any] = {}
        self.output_template: dict[str, Any] | None = None
        self.last_status: dict[str, Any] = {}
        self._scripts: asyncio.Queue[tuple[Any, list[Step], int]] = asyncio.Queue(
            PENDING_SCRIPTS)

    # -- requests ---------------------------------------------------------------------------
    def on_request(self, request: wire.Request) -> None:
        """Answer a request now, or queue its script; never waits."""
        try:
            answer = self._dispatch(request)
        except CommandError as exc:
            self.send(wire.error(request.id, _text(exc)))
            return
        if answer is not None:
            self.send(wire.result(request.id, answer))

    def _dispatch(self, request: wire.Request) -> dict[str, Any] | None:
        method, params, hub = request.method, request.params, self.hub
        if method == "info":
            return hub.info()
        if method == "list_endpoints":
            return {"endpoints": list(ENDPOINTS)}
        if method == "objects/list":
            return {"objects": list(hub.objects())}  # with the output pins
        if method == "objects/query":
            return self._query(_objects_param(params))
        if method == "objects/subscribe":
            return self._subscribe(_objects_param(params), params.get("response_template"))
        if method == "gcode/subscribe_output":
            self.output_template = _template(params.get("response_template"))
            return {}
        if method == "register_remote_method":
            return {}  # motiond calls no front-end method (Klipper's are for its own extras)
        if method == "gcode/help":
            return dict(gcode.HELP)
        if method == "emergency_stop":
            self._control("estop")
            return {}
        if method.startswith("pause_resume/") and method[13:] in ("pause", "resume", "cancel"):
            self._control(method[13:])
            return {}
        if method in ("gcode/restart", "gcode/firmware_restart"):
            self._queue(request.id, [Control("restart")])
            return None
        if method == "gcode/script":
            return self._script(request.id, params.get("script"))
        raise CommandError(Error.UNSUPPORTED, f"No registered endpoint '{method}'")

    def _query(self, wanted: dict[str, Any]) -> dict[str, Any]:
        now = self.hub.objects()
        return {"eventtime": _eventtime(), "status": objects.select(now, wanted)}

    def _subscribe(self, wanted: dict[str, Any], template: Any) -> dict[str, Any]:
        """Replace this connection's subscription; answer the current values."""
        self.subscription = wanted
        self.status_template = _template(template)
        answer = self._query(wanted)
        self.last_status = answer["status"]
        return answer

    def _script(self, request_id: Any, script: Any) -> dict[str, Any] | None:
        if not isinstance(script, str):
            raise CommandError(Error.UNSUPPORTED, "gcode/script: 'script' must be a string")
        if any(halts_at_once(line) for line in script.splitlines()):
            self._control("estop")  # on arrival, as from every other source
        steps = gcode.translate(script, self.hub.jog_feed_mm_min)
        if steps and all(isinstance(s, Control) and s.action in IMMEDIATE for s in steps):
            for step in steps:
                self._control(step.action)  # type: ignore[union-attr]
            return {}
        self._queue(request_id, steps)
        return None

    def _queue(self, request_id: Any, steps: list[Step]) -> None:
        """A script waits its turn with the stop generation it was sent in: a stop before
        it ran (or while it runs) ends it, whatever it waits for (a deferred jog too)."""
        try:
            self._scripts.put_nowait((request_id, steps, self.hub.ctx.ticket()))
        except asyncio.QueueFull as exc:
            raise CommandError(Error.BUSY, "too many G-code scripts waiting") from exc
        return None

    # -- scripts ----------------------------------------------------------------------------
    async def run_scripts(self) -> None:
        """Run queued scripts in order until cancelled; each is answered when it ends."""
        while True:
            request_id, steps, ticket = await self._scripts.get()
            try:
                for step in steps:
                    await self._step(step, ticket)
            except CommandError as exc:
                self.hub.output(f"!! {_text(exc)}")
                self.send(wire.error(request_id, _text(exc)))
                continue
            self.send(wire.result(request_id, {}))

    async def _step(self, step: Step, ticket: int) -> None:
        ctx = self.hub.ctx
        if not ctx.still_valid(ticket):
            raise CommandError(Error.BUSY, "a stop came after this script was sent: not run")
        if isinstance(step, Line):
            gcode.check_line_during_job(step.text, self.hub.job_state)
            try:
                messages = await ctx.run_gcode(step.text, ticket)
            except CommandError as exc:
                raise gcode.klipper_error(step.text, exc) from exc
            for message in messages:
                self.hub.output(response_text(message))
        elif isinstance(step, StartJob):
            await ctx.start_job(step.name, ticket)
        elif isinstance(step, SetPin):
            line = outputs.set_pin_line(ctx.status(), step.pin, step.value)
            await self._step(Line(line), ticket)
        elif isinstance(step, FeedOverride):
            ctx.control.set_feed_override(step.percent)
        elif isinstance(step, Message):
            self.hub.set_message(step.text)
        elif isinstance(step, GcodeOffset):
            await self._gcode_offset(step, ticket)
        elif step.action == "help":
            self.hub.output("\n".join(["// Available commands:",
                                       *(f"// {k}: {v}" for k, v in gcode.HELP.items())]))
        elif step.action == "velocity_limit":
            toolhead = self.hub.objects()["toolhead"]
            self.hub.output(gcode.velocity_report(toolhead["max_velocity"],
                                                  toolhead["max_accel"]))
        elif step.action == "restart":  # a reset board, as Klipper's restarts leave it
            ctx.control.reset()
            await ctx.run_gcode("$X")
            await ctx.run_gcode("M84")  # motors off, homing lost: as after Klipper's restart
            self.hub.restart()
        else:
            self._control(step.action)

    async def _gcode_offset(self, step: GcodeOffset, ticket: int) -> None:
        """Once the queued moves ran: optionally jog by the change, then ``G92`` so that the
        work offset (``homing_origin``) is the one asked for."""
        ctx = self.hub.ctx
        job = ctx.status().get("job") or {}
        if job.get("state") in ("running", "paused"):  # never applied late, when it ends
            raise CommandError(Error.BUSY, "SET_GCODE_OFFSET: a job is running")
        await ctx.moves.wait_idle()
        status = ctx.status()
        wpos, wco = status["wpos"], status["wco"]
        names = ctx.core.axis_names
        deltas: dict[str, float] = {}
        for axis in sorted(set(step.absolute) | set(step.adjust)):
            if axis not in names:
                raise CommandError(Error.UNSUPPORTED, f"SET_GCODE_OFFSET: no axis {axis}")
            index = names.index(axis)
            target = step.absolute.get(axis, wco[index]) + step.adjust.get(axis, 0.0)
            deltas[axis] = target - wco[index]
        if not deltas:
            return
        scale = 25.4 if status.get("modal", {}).get("units") == "in" else 1.0
        if step.move:
            speed_mm_min = 60.0 * (step.speed_mm_s or self.hub.jog_feed_mm_min / 60.0)
            words = " ".join(f"{axis}{delta:.4f}" for axis, delta in deltas.items())
            await ctx.run_gcode(f"$J=G21 G91 {words} F{speed_mm_min:.0f}", ticket)
            await ctx.moves.wait_idle()
            stay = {axis: wpos[names.index(axis)] for axis in deltas}
        else:
            stay = {axis: wpos[names.index(axis)] - delta for axis, delta in deltas.items()}
        await ctx.run_gcode("G92 " + " ".join(f"{a}{v / scale:.4f}" for a, v in stay.items()),
                            ticket)

    def _control(self, action: str) -> None:
        controls = self.hub.ctx.control
        if action == "pause":
            controls.hold()
        elif action == "resume":
            controls.resume()
        elif action == "cancel":
            controls.cancel_job()
        elif action == "estop":
            controls.emergency_stop()

    # -- pushes -----------------------------------------------------------------------------
    def push_status(self, now: dict[str, Any]) -> None:
        """Send what changed in the subscribed objects since the last push (if anything)."""
        if not self.subscription:
            return
        current = objects.select(now, self.subscription)
        changed = objects.diff(self.last_status, current)
        self.last_status = current
        if changed:
            params = {"eventtime": _eventtime(), "status": changed}
            self.send(wire.push(self.status_template, params))

    def push_output(self, text: str) -> None:
        if self.output_template is not None:
            self.send(wire.push(self.output_template, {"response": text}))


def response_text(message: str) -> str:
    """A motiond reply line as Klipper's console shows it: ``[MSG:x]`` is ``// x``; alarms
    and errors are ``!! ...``; M114's ``C: X:..`` loses the ``C:`` (Klipper's M114 starts at
    ``X:``, and the front-ends hide ``C:`` lines as temperature reports)."""
    if message.startswith("C: X:"):
        return message[3:]
    if message.startswith("[MSG:") and message.endswith("]"):
        return f"// {message[5:-1]}"
    if message.startswith(("ALARM:", "error:")):
        return f"!! {message}"
    return message


def _text(exc: CommandError) -> str:
    return f"error:{int(exc.code)} {exc.message}".strip()


def _objects_param(params: dict[str, Any]) -> dict[str, Any]:
    wanted = params.get("objects")
    if not isinstance(wanted, dict) or not all(
            isinstance(name, str) and (fields is None or isinstance(fields, list))
            for name, fields in wanted.items()):
        raise CommandError(Error.UNSUPPORTED, "'objects' must map names to field lists or null")
    return wanted


def _template(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise CommandError(Error.UNSUPPORTED, "'response_template' must be an object")
    return {key: item for key, item in value.items() if key != "params"}


def _eventtime() -> float:
    return round(os.times().elapsed, 3)
