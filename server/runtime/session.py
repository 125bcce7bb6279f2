"""One client connection, whatever the transport: protocol in, dispatcher, replies out.

A transport creates a :class:`Session`, feeds it bytes (or WebSocket text) and drains its
:class:`Outbox`. The session:

* acts on realtime bytes at once (status, hold, resume, reset, overrides, jog cancel), even
  while lines wait for planner room, and on ``M112`` the moment its line arrives;
* queues complete lines (bounded) and executes them one at a time through the dispatcher,
  answering each with exactly one ``ok`` or ``error:N`` in order. A line answered downstream
  (a Grbl controller behind motiond) is deferred: the next lines execute while it sits in the
  controller's buffer, and the replies behind it wait for its answer (at most
  :data:`INBOUND_LINES` of them), so the order holds;
* keeps taking bytes while its line queue is full: they wait in a
  :class:`~server.runtime.backlog.Backlog` (``[protocol] backlog_bytes``) whose realtime bytes
  are acted on as they arrive, so a sender that streams ahead without character counting can
  still hold (``!``) or reset (Ctrl-X) at once. Byte transports stop reading only while the
  backlog is full (:meth:`wait_input_room`). WebSocket messages (whose end ends a line) are
  never held back: that transport stops reading while the line queue is full
  (:meth:`wait_room`);
* answers ``?`` at most ``[protocol] status_reports_per_s`` times a second per connection
  (bursts of :data:`STATUS_BURST`); requests beyond that share the next report, sent as soon
  as one is allowed: at most one report is ever pending, nothing queues up;
* ``$AUTH=token`` logs in (see :mod:`server.runtime.login_guard`: constant-time comparison, wrong
  tokens answered ever later per client address, the connection closed after
  ``auth_failures_per_connection``). An observer never logs in. A session on probation (it got
  a TCP slot reserved for logged-in connections) must log in with its first line;
* bounds what it sends: a client that stops reading overflows its outbox and is disconnected,
  never slowing motion or other clients. :meth:`end` says why in a ``[MSG:]`` line, then the
  transport hangs up once that is sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import time
from collections import deque
from typing import TYPE_CHECKING

from server.errors import Alarm, CommandError, Error
from server.protocol.events import (
    Event,
    LineReceived,
    LineRejected,
    Realtime,
    RealtimeReceived,
)
from server.protocol.lines import LineProtocol
from server.protocol.reports import StatusScheduler
from server.runtime.backlog import Backlog
from server.runtime.control import halts_at_once
from server.runtime.events import Event as BusEvent
from server.runtime.login_guard import LoginGuard, token_matches
from server.runtime.outbox import BoundedQueue
from server.runtime.ratelimit import TokenBucket
from server.runtime.status import snapshot

if TYPE_CHECKING:
    from server.runtime.kernel import Kernel

log = logging.getLogger("motiond.session")
_AUTH = re.compile(r"^\s*\$AUTH=(.*)$", re.I)
INBOUND_LINES = 64
REFILL_BYTES = 1024  # held-back input is fed to the protocol in slices of this size
STATUS_BURST = 5
PROBATION_REFUSED = "this slot is reserved for logged-in connections: send $AUTH=<token> first"
YIELD_AFTER_S = 0.001  # the executor gives other tasks a turn at least this often
__all__ = ["INBOUND_LINES", "Outbox", "Session", "line_token", "token_matches"]


class Outbox(BoundedQueue[bytes]):
    """What one line-protocol client is sent, bounded in bytes, drained as one chunk."""

    async def get(self) -> bytes | None:
        """Everything queued so far as one chunk, or None once closed."""
        chunks = await self.get_all()
        return None if chunks is None else b"".join(chunks)


class Session:
    """See the module docstring. Owns one task: the line executor.

    Args:
        peer: the client's address, for the login guard and the log.
        guard: shared by a transport's sessions, so wrong tokens are slowed per address
            across connections; by default the session has its own.
        must_login: probation: the first line must be ``$AUTH=`` the right token.
    """

    def __init__(
        self,
        kernel: Kernel,
        name: str,
        *,
        websocket: bool = False,
        token: str | None = None,
        observer: bool = False,
        peer: str = "local",
        guard: LoginGuard | None = None,
        must_login: bool = False,
    ) -> None:
        core = kernel.config.core
        self.kernel = kernel
        self.name = name
        self.peer = peer
        self._token = line_token(kernel)
        self._observer = observer
        self.on_probation = must_login and self._token is not None
        self.can_control = self._token is None or token_matches(token, self._token)
        self.may_observe = self.can_control or core.protocol.unauthenticated == "read-only"
        if observer:  # asked to only watch: status and pushes, never control
            self.can_control = False
        if self.on_probation:
            self.can_control = self.may_observe = False
        self._websocket = websocket
        self.protocol = LineProtocol(
            line_limit=core.protocol.line_limit, dialect=core.protocol.dialect, websocket=websocket
        )
        self.outbox = Outbox(core.protocol.outgoing_limit_bytes)
        self._guard = guard if guard is not None else login_guard(kernel)
        self._auth_failures = 0
        self._ending: str | None = None
        self._lines: deque[tuple[int, LineReceived | LineRejected]] = deque()
        self._lines_ready = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._backlog = Backlog(core.protocol.backlog_bytes)
        self._input_room = asyncio.Event()
        self._input_room.set()
        self._stopping = asyncio.Event()
        self._epoch = 0
        self._queued_bytes = 0
        self._scheduler = StatusScheduler()
        self._status_bucket = TokenBucket(
            core.protocol.status_reports_per_s, STATUS_BURST, time.monotonic())
        self._status_timer: asyncio.TimerHandle | None = None
        self._unsubscribe = kernel.events.subscribe(BusEvent.PUSH, self.push)
        self._task: asyncio.Task[None] | None = None
        self._replies: deque[tuple[int, asyncio.Future[bytes]]] = deque()  # behind a deferred
        self._replies_room = asyncio.Event()
        self._closing = False
        self._closed = False

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> None:
        """Send the banner and start executing lines."""
        self.outbox.put(self.protocol.banner())
        self._task = asyncio.get_running_loop().create_task(self._executor(), name=self.name)

    async def close(self) -> None:
        """Stop taking lines. A line already executing completes (a line is all or nothing:
        an arc is never half queued); lines not yet started were never acknowledged and are
        dropped. Motion already accepted keeps running (or holds, with hold_on_disconnect).
        Repeatable."""
        hold = self.kernel.config.core.machine.hold_on_disconnect and self.can_control
        if hold and not self._closed:
            self.kernel.machine.feed_hold()
        self._closed = True
        self._stop_input()
        self.outbox.close()
        if self._task is not None:
            await self._task
            self._task = None

    def end(self, reason: str) -> None:
        """Hang up: a last ``[MSG:reason]`` line, then the outbox closes; the transport closes
        the connection once that is sent."""
        if self.outbox.closed:
            return
        self.outbox.put(self.protocol.push(f"[MSG:{reason}]"))
        log.info("%s: %s", self.name, reason)
        self._stop_input()
        self.outbox.close()

    def _stop_input(self) -> None:
        self._unsubscribe()
        self._closing = True
        self._stopping.set()
        if self._status_timer is not None:
            self._status_timer.cancel()
            self._status_timer = None
        self._lines.clear()
        self._backlog.clear()
        self._lines_ready.set()
        self._room.set()
        self._input_room.set()
        self._replies_room.set()

    @property
    def closed(self) -> bool:
        return self.outbox.closed

    @property
    def backlog_full(self) -> bool:
        """Input is held back up to its bound: the transport should stop reading."""
        return not self._input_room.is_set()

    # -- input ------------------------------------------------------------------------------
    def receive_data(self, data: bytes) -> None:
        """Bytes from the client (TCP, serial, pty; a binary WebSocket message)."""
        while data:
            if self._websocket or not (self._backlog or len(self._lines) >= INBOUND_LINES):
                self._handle(self.protocol.receive_data(data))
                return
            reset_at = data.find(b"\x18") if self.can_control else -1
            if reset_at < 0:
                self._hold_back(data)
                return
            self._hold_back(data[:reset_at])
            self._realtime(Realtime.RESET)  # drops what is held, as Grbl empties its buffer
            data = data[reset_at + 1 :]

    def receive_text(self, text: str) -> None:
        """A WebSocket text frame."""
        self._handle(self.protocol.receive_text(text))

    async def wait_room(self) -> None:
        """Wait while too many lines are queued (the WebSocket transport stops reading)."""
        await self._room.wait()

    async def wait_input_room(self) -> None:
        """Wait while the backlog is full (a byte transport stops reading meanwhile)."""
        await self._input_room.wait()

    def _hold_back(self, data: bytes) -> None:
        """The line queue is full: keep the bytes, act on their realtime commands now."""
        reported = False
        for event in self._backlog.hold(self.protocol, data):
            if isinstance(event, RealtimeReceived):
                reported = self._on_realtime(event.command, reported)
            elif self._is_emergency_stop(event):
                self.kernel.control.emergency_stop()
        if self._backlog.full:
            self._input_room.clear()

    def _handle(self, events: list[Event], *, replayed: bool = False) -> None:
        """Protocol events in stream order; ``replayed``: from held-back bytes, whose realtime
        commands and M112 were acted on when they arrived."""
        reported = False
        for event in events:
            if isinstance(event, RealtimeReceived):
                if not replayed:
                    reported = self._on_realtime(event.command, reported)
                continue
            if not replayed and self._is_emergency_stop(event):
                self.kernel.control.emergency_stop()
            self._lines.append((self._epoch, event))
            self._queued_bytes += _size(event)
            if len(self._lines) >= INBOUND_LINES:
                self._room.clear()
        self._lines_ready.set()

    def _on_realtime(self, command: Realtime, reported: bool) -> bool:
        """Act on one realtime byte; like Grbl's status flag, one report per batch of '?'."""
        if command is Realtime.STATUS:
            if not reported:
                self._realtime(command)
            return True
        self._realtime(command)
        return reported

    def _is_emergency_stop(self, event: Event) -> bool:
        """M112 from a connection that may control: acted on the moment its line arrives."""
        if not isinstance(event, LineReceived) or not self.can_control:
            return False
        return halts_at_once(event.text)

    def _refill(self) -> None:
        """Feed held-back bytes to the protocol until the line queue is full again."""
        while self._backlog and len(self._lines) < INBOUND_LINES:
            self._handle(self.protocol.receive_data(self._backlog.take(REFILL_BYTES)),
                         replayed=True)
        if not self._backlog.full:
            self._input_room.set()

    def _realtime(self, command: Realtime) -> None:
        if not self.may_observe:
            return
        if command is Realtime.STATUS:
            self._request_status()
            return
        if not self.can_control:
            return
        if command is Realtime.RESET:
            self._epoch += 1
            self._lines.clear()
            self._queued_bytes = 0
            self._backlog.clear()
            self._room.set()
            self._input_room.set()
            self.protocol.reset()
            self._scheduler.refresh()
            self.kernel.control.reset()
            self.outbox.put(self.protocol.banner())
            return
        self.kernel.control.realtime(command)

    # -- status reports ---------------------------------------------------------------------
    def _request_status(self) -> None:
        """Report now if this connection's rate allows, else once as soon as it does."""
        if self._status_timer is not None or self._closing:
            return  # shares the report already pending
        wait_s = self._status_bucket.take(time.monotonic())
        if wait_s <= 0:
            self.outbox.put(self.protocol.push(self._status()))
            return
        loop = asyncio.get_running_loop()
        self._status_timer = loop.call_later(wait_s, self._pending_status)

    def _pending_status(self) -> None:
        self._status_timer = None
        self._request_status()

    def _status(self) -> str:
        core = self.kernel.config.core
        held = self._queued_bytes + len(self._backlog)
        free = max(0, core.protocol.rx_buffer_bytes - held)
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

    def _reply_ok(self, messages: list[str]) -> bytes:
        try:
            return self.protocol.reply_ok(messages)
        except ValueError:
            log.warning("%s: dropped reply lines not safe for senders: %r", self.name, messages)
            return self.protocol.reply_ok()

    # -- logging in -------------------------------------------------------------------------
    async def _login(self, given: str) -> bytes:
        """``$AUTH=token``: this connection may control the machine from now on."""
        if self._observer:
            return self._refuse("an observer connection never controls the machine")
        if self._token is None:
            return self.protocol.reply_ok()
        if token_matches(given.strip(), self._token):
            self.can_control = self.may_observe = True
            self.on_probation = False
            self._guard.succeeded(self.peer)
            return self.protocol.reply_ok()
        self._auth_failures += 1
        delay_s = self._guard.failed(self.peer, self.name)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._stopping.wait(), delay_s)
        limit = self.kernel.config.core.protocol.auth_failures_per_connection
        if self.on_probation or self._auth_failures >= limit:
            self._ending = f"{self._auth_failures} wrong token(s): closing the connection"
        return self._refuse("wrong token")

    def _refuse(self, message: str) -> bytes:
        return self.protocol.reply_error(CommandError(Error.AUTH_REQUIRED, message))

    # -- executing lines --------------------------------------------------------------------
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
            if self._backlog and len(self._lines) < INBOUND_LINES // 2:
                self._refill()
            reply = await self._execute(event, epoch)
            if len(self._lines) < INBOUND_LINES // 2:
                self._room.set()
            if epoch == self._epoch:
                self._queued_bytes = max(0, self._queued_bytes - _size(event))
                self._answer(reply, epoch)
            while len(self._replies) >= INBOUND_LINES and not self._closing:
                self._replies_room.clear()
                await self._replies_room.wait()
            if self._ending is not None:
                self.end(self._ending)
                return
            if loop.time() - turn_s > YIELD_AFTER_S:  # lines that never wait must not hog
                await asyncio.sleep(0)
                turn_s = loop.time()

    def _answer(self, reply: bytes | asyncio.Future[bytes], epoch: int) -> None:
        """Send a line's reply, or queue it behind the deferred replies still pending."""
        if isinstance(reply, bytes):
            if not self._replies:
                self.outbox.put(reply)
                return
            ready: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
            ready.set_result(reply)
            reply = ready
        self._replies.append((epoch, reply))
        reply.add_done_callback(self._flush_replies)

    def _flush_replies(self, _: object = None) -> None:
        """Send the replies at the head of the queue that are ready, in order."""
        while self._replies and self._replies[0][1].done():
            epoch, reply = self._replies.popleft()
            if epoch == self._epoch and not reply.cancelled():
                self.outbox.put(reply.result())
        if len(self._replies) < INBOUND_LINES:
            self._replies_room.set()

    def _later(self, messages: list[str],
               deferred: list[asyncio.Future[list[str]]]) -> asyncio.Future[bytes]:
        """The reply of a deferred line: ``messages`` and its answers, or the first error."""
        reply: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()

        def done(_: object) -> None:
            if reply.done() or not all(future.done() for future in deferred):
                return
            lines = list(messages)
            for future in deferred:
                error = CommandError(Error.BUSY, "cancelled") if future.cancelled() else (
                    future.exception())
                if isinstance(error, CommandError):
                    reply.set_result(self.protocol.reply_error(error))
                    return
                if error is not None:
                    log.error("deferred line failed: %r", error)
                    reply.set_result(self.protocol.reply_error(
                        CommandError(Error.UNSUPPORTED, "internal error")))
                    return
                lines += future.result()
            reply.set_result(self._reply_ok(lines))

        for future in deferred:
            future.add_done_callback(done)
        return reply

    async def _execute(
        self, event: LineReceived | LineRejected, epoch: int
    ) -> bytes | asyncio.Future[bytes]:
        if isinstance(event, LineRejected):
            return self.protocol.reply_error(event.error)
        if event.handled:  # M110: the protocol already set the line number
            return self.protocol.reply_ok()
        login = _AUTH.match(event.text)
        if login is not None:
            return await self._login(login.group(1))
        if self.on_probation:
            self._ending = PROBATION_REFUSED
            return self._refuse("log in first")
        if not self.may_observe:
            return self._refuse("log in with $AUTH=")
        deferred: list[asyncio.Future[list[str]]] = []
        try:
            messages = await self.kernel.dispatcher.submit(
                event.text, self, still_valid=lambda: epoch == self._epoch,
                defer=deferred.append)
        except CommandError as exc:
            return self.protocol.reply_error(exc)
        except Exception as exc:  # noqa: BLE001 - unexpected: alarm, answer, keep serving
            log.exception("line %r failed", event.text)
            self.kernel.alarm(Alarm.MODULE_FAILED, f"internal error on {event.text!r}: {exc!r}")
            return self.protocol.reply_error(CommandError(Error.UNSUPPORTED, "internal error"))
        if deferred:
            return self._later(messages, deferred)
        return self._reply_ok(messages)


def line_token(kernel: Kernel) -> str | None:
    """The token line-protocol connections must present (config, else ``$MOTIOND_TOKEN``)."""
    return kernel.config.core.protocol.token or os.environ.get("MOTIOND_TOKEN") or None


def login_guard(kernel: Kernel) -> LoginGuard:
    """A guard for one transport's sessions, from ``[protocol]``."""
    config = kernel.config.core.protocol
    return LoginGuard(config.auth_delay_s, config.auth_max_delay_s)


def _size(event: LineReceived | LineRejected) -> int:
    """Bytes a line took in the client's view of our input buffer (newline included)."""
    return len(event.text) + 1 if isinstance(event, LineReceived) else 1
