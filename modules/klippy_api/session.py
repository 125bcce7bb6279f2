"""One client of Klipper's API socket (Moonraker): its requests and subscriptions.

Requests are answered at once, but ``gcode/script``, whose scripts run one after another
(:mod:`modules.klippy_api.scripts`). A malformed request (:class:`wire.Malformed`, a
parameter of the wrong type, a ``response_template`` that cannot be sent back) is answered
with an error and changes nothing; the connection goes on.

The session never writes to a socket: :attr:`Session.send` takes each message (the transport
queues it, bounded).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any

from modules.klippy_api import gcode, objects, wire
from modules.klippy_api.gcode import Control
from modules.klippy_api.hub import Hub
from modules.klippy_api.scripts import Script, Scripts, control, error_text
from modules.klippy_api.scripts import response_text as response_text  # re-exported
from server.errors import CommandError, Error

TEMPLATE_BYTES = 512  # a response_template as JSON (Moonraker's: 40 bytes)
ENDPOINTS = ("info", "list_endpoints", "objects/list", "objects/query", "objects/subscribe",
             "gcode/script", "gcode/help", "gcode/subscribe_output", "gcode/restart",
             "gcode/firmware_restart", "emergency_stop", "register_remote_method",
             "pause_resume/pause", "pause_resume/resume", "pause_resume/cancel")


class Session:
    """One connection's state: subscription, output subscription, queued scripts."""

    def __init__(self, hub: Hub, send: Callable[[dict[str, Any]], None]) -> None:
        self.hub, self.send = hub, send
        self.subscription: dict[str, list[str] | None] = {}
        self.status_template: dict[str, Any] = {}
        self.output_template: dict[str, Any] | None = None
        self.last_status: dict[str, Any] = {}
        self.scripts = Scripts(hub, send)

    # -- requests ---------------------------------------------------------------------------
    async def on_request(self, request: wire.Item) -> None:
        """Answer a request now, or queue its script; waits only for the loop budget (a
        long script is searched for ``M112`` in pieces)."""
        if isinstance(request, wire.Malformed):
            self.send(wire.error(request.id, request.message))
            return
        try:
            answer = await self._dispatch(request)
        except CommandError as exc:
            self.send(wire.error(request.id, error_text(exc)))
            return
        if answer is not None:
            self.send(wire.result(request.id, answer))

    async def _dispatch(self, request: wire.Request) -> dict[str, Any] | None:
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
            control(hub.ctx, "estop")
            return {}
        if method.startswith("pause_resume/") and method[13:] in ("pause", "resume", "cancel"):
            control(hub.ctx, method[13:])
            return {}
        if method in ("gcode/restart", "gcode/firmware_restart"):
            self.scripts.queue(Script(request.id, [Control("restart")], "", 0, hub.ctx.ticket()))
            return None
        if method == "gcode/script":
            script = params.get("script")
            if not isinstance(script, str):
                raise CommandError(Error.UNSUPPORTED, "gcode/script: 'script' must be a string")
            return await self.scripts.submit(request.id, script)
        raise CommandError(Error.UNSUPPORTED, f"No registered endpoint '{method}'")

    def _query(self, wanted: dict[str, Any]) -> dict[str, Any]:
        now = self.hub.objects()
        return {"eventtime": _eventtime(), "status": objects.select(now, wanted)}

    def _subscribe(self, wanted: dict[str, Any], template: Any) -> dict[str, Any]:
        """Replace this connection's subscription; answer the current values."""
        self.status_template = _template(template)
        self.subscription = wanted
        answer = self._query(wanted)
        self.last_status = answer["status"]
        return answer

    def close(self) -> None:
        """The connection went: its waiting scripts are dropped."""
        self.scripts.close()

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


def _objects_param(params: dict[str, Any]) -> dict[str, Any]:
    wanted = params.get("objects")
    if not isinstance(wanted, dict) or not all(
            fields is None or (isinstance(fields, list)
                               and all(isinstance(key, str) for key in fields))
            for fields in wanted.values()):
        raise CommandError(Error.UNSUPPORTED,
                           "'objects' must map names to lists of field names or null")
    return wanted


def _template(value: Any) -> dict[str, Any]:
    """A ``response_template`` that every push can carry: an object of at most
    :data:`TEMPLATE_BYTES` as JSON (so never nested deep enough to fail later)."""
    if not isinstance(value, dict):
        raise CommandError(Error.UNSUPPORTED, "'response_template' must be an object")
    template = {key: item for key, item in value.items() if key != "params"}
    try:
        size_bytes = len(json.dumps(template, allow_nan=False))
    except (ValueError, TypeError, RecursionError):
        size_bytes = TEMPLATE_BYTES + 1
    if size_bytes > TEMPLATE_BYTES:
        raise CommandError(Error.UNSUPPORTED,
                           f"'response_template' must be at most {TEMPLATE_BYTES} bytes of JSON")
    return template


def _eventtime() -> float:
    return round(os.times().elapsed, 3)
