"""Commands from the broker: ``<prefix>/cmd/gcode``, ``cmd/realtime`` and ``cmd/job``.

Every message gets a reply on ``<prefix>/reply`` (one per G-code line), carrying the request's
``id``. With ``allow_control = false`` every command is refused (``control_disabled``); a
malformed payload is refused whole (``invalid_payload``) and changes nothing. A retained
message (published with the retain flag) is refused (``retained``) and never executed, and the
same stored message is not answered again when the broker sends it after a reconnect. The
broker's ACLs decide who may publish here: this module obeys whatever the broker delivers.

G-code lines run through ``ModuleContext.run_gcode``, the one ordered path of every source,
so they wait their turn, are refused while another source's motion or a job runs (error 45),
and are locked out in ALARM. They run in a task of their own, one message after another, so
that a line waiting for planner room never delays a ``hold`` or ``reset``; at most
``PENDING_BATCHES`` messages wait (more are refused ``busy``). A reset drops the lines that
have not started (each answered ``busy``). An M112 line stops the machine as it arrives, ahead
of the lines waiting, as it does from a sender or the JSON API. A ``cmd/job`` waits its turn
in the same task: starting a job first checks that it fits the travel from the current work
origin (``ModuleContext.start_job``), which reads the whole file.
"""

from __future__ import annotations

import asyncio
import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from modules.mqtt.payloads import (
    Gcode,
    Invalid,
    Realtime,
    StartJob,
    error_reply,
    ok_reply,
    parse_request,
    peek_id,
)
from server.errors import CommandError, Error
from server.gcode.parser import check_length
from server.kernel.control import halts_at_once
from server.kernel.module import ModuleContext

PENDING_BATCHES = 16
RETAINED_REMEMBERED = 256  # retained commands already refused, not answered again
RETAINED_REFUSED = ("a retained command is never executed (it would run again at every start "
                    "and reconnect): publish commands without the retain flag, and clear this "
                    "one with an empty retained message")
Reply = Callable[[dict[str, Any]], None]


@dataclass(frozen=True, slots=True)
class _Batch:
    request: Gcode | StartJob
    ticket: int  # the stop generation the message arrived in: after a stop, none of it runs


class Control:
    """Turns command messages into actions on the machine and replies."""

    def __init__(
        self, ctx: ModuleContext, reply: Reply, *, allowed: bool, max_lines: int,
        max_payload_bytes: int,
    ) -> None:
        self.ctx, self.reply = ctx, reply
        self.allowed, self.max_lines, self.max_payload_bytes = allowed, max_lines, max_payload_bytes
        self.refused = 0  # messages refused whole (disabled, malformed, busy)
        self._batches: asyncio.Queue[_Batch] = asyncio.Queue(PENDING_BATCHES)
        self._retained_seen: dict[tuple[str, bytes], None] = {}  # refused, oldest first

    def on_command(self, command: str, payload: bytes, *, retained: bool = False) -> None:
        """One message on ``cmd/<command>``; never waits, never raises for a bad message.

        A retained message is never executed: it would run again at every start and every
        reconnect. It is refused once (``retained``), and not again when the broker sends
        the same stored message after a reconnect."""
        if retained:
            self._refuse_retained(command, payload)
            return
        if not self.allowed:
            self._refuse(peek_id(payload[:4096]), command, "control_disabled",
                         "control is disabled on this machine (allow_control = false)",
                         Error.AUTH_REQUIRED)
            return
        if len(payload) > self.max_payload_bytes:
            self._refuse(None, command, "invalid_payload",
                         f"payload larger than {self.max_payload_bytes} bytes")
            return
        request = parse_request(command, payload, self.max_lines)
        if isinstance(request, Invalid):
            self._refuse(request.id, command, "invalid_payload", request.message)
        elif isinstance(request, Realtime):
            self._realtime(request)
        elif isinstance(request, StartJob):
            self._queue(request)
        else:
            if any(halts_at_once(line) for line in request.lines):
                self.ctx.control.emergency_stop()  # on arrival, as from every other source
            self._queue(request)

    def _refuse_retained(self, command: str, payload: bytes) -> None:
        if not payload:
            return  # an empty retained message clears the stored one: nothing to answer
        key = (command, hashlib.sha256(payload).digest())
        if key in self._retained_seen:
            return
        self._retained_seen[key] = None
        while len(self._retained_seen) > RETAINED_REMEMBERED:
            self._retained_seen.pop(next(iter(self._retained_seen)))
        self._refuse(peek_id(payload[:4096]), command, "retained", RETAINED_REFUSED)

    def _refuse(self, request_id: str | int | None, command: str, reason: str, message: str,
                code: int | None = None) -> None:
        self.refused += 1
        self.reply(error_reply(request_id, command, reason, message, code))

    def _realtime(self, request: Realtime) -> None:
        controls = self.ctx.control
        action = {"hold": controls.hold, "resume": controls.resume, "reset": controls.reset}
        action[request.command]()  # a reset is a stop: the batches waiting are void
        self.reply(ok_reply(request.id, "realtime", action=request.command))

    async def _start_job(self, request: StartJob, ticket: int) -> None:
        try:
            await self.ctx.start_job(request.name, ticket)
        except CommandError as exc:
            self.reply(error_reply(request.id, "job", "refused", _text(exc), int(exc.code)))
            return
        self.reply(ok_reply(request.id, "job", name=request.name))

    def _queue(self, request: Gcode | StartJob) -> None:
        try:
            self._batches.put_nowait(_Batch(request, self.ctx.ticket()))
        except asyncio.QueueFull:
            self.refused += 1
            if isinstance(request, StartJob):
                self.reply(error_reply(request.id, "job", "busy", "too many messages waiting",
                                       Error.BUSY))
                return
            for index, line in enumerate(request.lines):
                self.reply(error_reply(request.id, "gcode", "busy",
                                       "too many G-code messages waiting", Error.BUSY,
                                       index=index, line=line))

    async def run(self) -> None:
        """Run queued G-code messages, one line at a time, until cancelled."""
        limit = self.ctx.core.protocol.line_limit
        while True:
            batch = await self._batches.get()
            request = batch.request
            if isinstance(request, StartJob):
                await self._start_job(request, batch.ticket)
                continue
            for index, line in enumerate(request.lines):
                self.reply(await self._line(batch, line, limit) | {"index": index, "line": line})

    async def _line(self, batch: _Batch, line: str, limit: int) -> dict[str, Any]:
        request_id = batch.request.id
        try:
            check_length(line, limit)
            messages = await self.ctx.run_gcode(line, batch.ticket)
        except CommandError as exc:
            return error_reply(request_id, "gcode", "refused", _text(exc), int(exc.code))
        return ok_reply(request_id, "gcode", messages=messages)


def _text(exc: CommandError) -> str:
    return f"error:{int(exc.code)} {exc.message}".strip()
