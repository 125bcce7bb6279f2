"""One client connection, whatever the transport: protocol in, dispatcher, replies out.

A transport creates a :class:`Session`, feeds it bytes (or WebSocket text) and drains its
:class:`Outbox`. The session:

* acts on realtime bytes at once (status, hold, resume, reset, overrides, jog cancel), even
  while lines wait for planner room, and on ``M112`` the moment its line arrives;
* queues complete lines (bounded) and executes them one at a time through the dispatcher,
  answering each with exactly one ``ok`` or ``error:N`` in order;
* bounds what it sends: a client that stops reading overflows its outbox and is disconnected,
  never slowing motion or other clients.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import os
import re
from collections import deque
from typing import TYPE_CHECKING

from server.errors import AUTH_REQUIRED, CommandError
from server.outbox import BoundedQueue
from server.protocol import (
    LineProtocol,
    LineReceived,
    LineRejected,
    Realtime,
    RealtimeReceived,
)
from server.reports import ALARM_MODULE_FAILED, StatusScheduler
from server.status import snapshot

if TYPE_CHECKING:
    from server.kernel import Kernel

log = logging.getLogger("motiond.session")
_AUTH = re.compile(r"^\s*\$AUTH=(.*)$", re.I)
_M112 = re.compile(r"^\s*(?:N\d+\s*)?M\s*0*112(?:\D|$)", re.I)
INBOUND_LINES = 64
YIELD_AFTER_S = 0.001  # the executor gives other tasks a turn at least this often


class Outbox(BoundedQueue[bytes]):
    """What one line-protocol client is sent, bounded in bytes, drained as one chunk."""

    async def get(self) -> bytes | None:
        """Everything queued so far as one chunk, or None once closed."""
        chunks = await self.get_all()
        return None if chunks is None else b"".join(chunks)


class Session:
    """See the module docstring. Owns one task: the line executor."""

    def __init__(
        self,
        kernel: Kernel,
        name: str,
        *,
        websocket: bool = False,
        token: str | None = None,
        observer: bool = False,
    ) -> None:
        core = kernel.config.core
        self.kernel = kernel
        self.name = name
        self._token = line_token(kernel)
        self.can_control = self._token is None or token_matches(token, self._token)
        self.may_observe = self.can_control or core.protocol.unauthenticated == "read-only"
        if observer:  # asked to only watch: status and pushes, never control
            self.can_control = False
        self.protocol = LineProtocol(
            line_limit=core.protocol.line_limit, dialect=core.protocol.dialect, websocket=websocket
        )
        self.outbox = Outbox(core.protocol.outgoing_limit_bytes)
        self._lines: deque[tuple[int, LineReceived | LineRejected]] = deque()
        self._lines_ready = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._epoch = 0
        self._queued_bytes = 0
        self._scheduler = StatusScheduler()
        self._unsubscribe = kernel.events.subscribe("push", self.push)
        self._task: asyncio.Task[None] | None = None
        self._closing = False

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        """Send the banner and start executing lines."""
        self.outbox.put(self.protocol.banner())
        self._task = asyncio.get_running_loop().create_task(self._executor(), name=self.name)

    async def close(self) -> None:
        """Stop taking lines. A line already executing completes (a line is all or nothing:
        an arc is never half queued); lines not yet started were never acknowledged and are
        dropped. Motion already accepted keeps running (or holds, with hold_on_disconnect)."""
        self._unsubscribe()
        self.outbox.close()
        self._closing = True
        if self.kernel.config.core.machine.hold_on_disconnect and self.can_control:
            self.kernel.machine.feed_hold()
        self._lines.clear()
        self._lines_ready.set()
        if self._task is not None:
            await self._task
            self._task = None

    @property
    def closed(self) -> bool:
        return self.outbox.closed

    # -- input ------------------------------------------------------------------------------
    def receive_data(self, data: bytes) -> None:
        """Bytes from the client (TCP, serial)."""
        self._handle(self.protocol.receive_data(data))

    def receive_text(self, text: str) -> None:
        """A WebSocket text frame."""
        self._handle(self.protocol.receive_text(text))

    async def wait_room(self) -> None:
        """Wait while too many lines are queued (the transport stops reading meanwhile)."""
        await self._room.wait()

    def _handle(self, events: list[LineReceived | LineRejected | RealtimeReceived]) -> None:
        reported = False
        for event in events:
            if isinstance(event, RealtimeReceived):
                if event.command is Realtime.STATUS:
                    if reported:  # like Grbl's status flag: one report per batch of '?'
                        continue
                    reported = True
                self._realtime(event.command)
                continue
            if isinstance(event, LineReceived) and _M112.match(event.text) and self.can_control:
                self.kernel.machine.emergency_stop()
            self._lines.append((self._epoch, event))
            self._queued_bytes += _size(event)
            if len(self._lines) >= INBOUND_LINES:
                self._room.clear()
        self._lines_ready.set()

    def _realtime(self, command: Realtime) -> None:
        if not self.may_observe:
            return
        if command is Realtime.STATUS:
            self.outbox.put(self.protocol.push(self._status()))
            return
        if not self.can_control:
            return
        if command is Realtime.RESET:
            self._epoch += 1
            self._lines.clear()
            self._queued_bytes = 0
            self._room.set()
            self.protocol.reset()
            self._scheduler.refresh()
            self.kernel.machine.soft_reset()
            self.outbox.put(self.protocol.banner())
            return
        self.kernel.machine.realtime(command)

    def _status(self) -> str:
        core = self.kernel.config.core
        free = max(0, core.protocol.rx_buffer_bytes - self._queued_bytes)
        return self._scheduler.report(
            snapshot(self.kernel, free),
            report_mask=core.machine.status_report_mask,
            inches=core.machine.report_inches,
        )

    # -- output -----------------------------------------------------------------------------
    def push(self, message: str) -> None:
        """An unsolicited line for this client (kernel ``push`` event)."""
        if not self.may_observe:
            return
        try:
            self.outbox.put(self.protocol.push(message))
        except ValueError:
            log.warning("dropped a push message that is not safe for senders: %r", message)

    def _login(self, given: str) -> bytes:
        """``$AUTH=token``: this connection may control the machine from now on."""
        if self._token is None or token_matches(given.strip(), self._token):
            self.can_control = self.may_observe = True
            return self.protocol.reply_ok()
        log.warning("%s: wrong token", self.name)
        return self.protocol.reply_error(CommandError(AUTH_REQUIRED, "wrong token"))

    async def _executor(self) -> None:
        loop = asyncio.get_running_loop()
        turn_s = loop.time()
        while not self._closing:
            if not self._lines:
                self._lines_ready.clear()
                await self._lines_ready.wait()
                turn_s = loop.time()
                continue
            epoch, event = self._lines.popleft()
            reply = await self._execute(event, epoch)
            if len(self._lines) < INBOUND_LINES // 2:
                self._room.set()
            if epoch == self._epoch:
                self._queued_bytes = max(0, self._queued_bytes - _size(event))
                self.outbox.put(reply)
            if loop.time() - turn_s > YIELD_AFTER_S:  # lines that never wait must not hog
                await asyncio.sleep(0)
                turn_s = loop.time()

    async def _execute(self, event: LineReceived | LineRejected, epoch: int) -> bytes:
        if isinstance(event, LineRejected):
            return self.protocol.reply_error(event.error)
        if event.handled:  # M110: the protocol already set the line number
            return self.protocol.reply_ok()
        login = _AUTH.match(event.text)
        if login is not None:
            return self._login(login.group(1))
        if not self.may_observe:
            return self.protocol.reply_error(CommandError(AUTH_REQUIRED, "log in with $AUTH="))
        try:
            messages = await self.kernel.dispatcher.submit(
                event.text, self, still_valid=lambda: epoch == self._epoch)
        except CommandError as exc:
            return self.protocol.reply_error(exc)
        except Exception as exc:  # noqa: BLE001 - unexpected: alarm, answer, keep serving
            log.exception("line %r failed", event.text)
            self.kernel.alarm(ALARM_MODULE_FAILED, f"internal error on {event.text!r}: {exc!r}")
            return self.protocol.reply_error(CommandError(20, "internal error"))
        return self.protocol.reply_ok(messages)


def line_token(kernel: Kernel) -> str | None:
    """The token line-protocol connections must present (config, else ``$MOTIOND_TOKEN``)."""
    return kernel.config.core.protocol.token or os.environ.get("MOTIOND_TOKEN") or None


def token_matches(given: str | None, expected: str) -> bool:
    return given is not None and hmac.compare_digest(given.encode(), expected.encode())


def _size(event: LineReceived | LineRejected) -> int:
    """Bytes a line took in the client's view of our input buffer (newline included)."""
    return len(event.text) + 1 if isinstance(event, LineReceived) else 1
