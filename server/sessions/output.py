"""A session's output: replies in order, rate-limited status reports and pushes, bounded.

:class:`SessionOutput` is the part of :class:`~server.sessions.session.Session` (a base class of
it) that writes to the client's :class:`Outbox`. It:

* answers each line with exactly one ``ok`` or ``error:N``, in order. A line answered
  downstream (a Grbl controller behind motiond) is deferred: the next lines execute while it
  sits in the controller's buffer, and the replies behind it wait for its answer (at most
  :data:`~server.sessions.input.INBOUND_LINES` of them), so the order holds;
* answers ``?`` at most ``[protocol] status_reports_per_s`` times a second per connection
  (bursts of :data:`STATUS_BURST`); requests beyond that share the next report, sent as soon
  as one is allowed: at most one report is ever pending, nothing queues up;
* bounds what it sends: a client that stops reading overflows its outbox and is disconnected,
  never slowing motion or other clients.

Its state is the session's, created by ``Session.__init__``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from server.errors import CommandError, Error
from server.kernel.status import snapshot
from server.sessions.input import INBOUND_LINES
from server.sessions.outbox import BoundedQueue

if TYPE_CHECKING:
    from collections import deque

    from server.kernel.kernel import Kernel
    from server.protocol.lines import LineProtocol
    from server.protocol.reports import StatusScheduler
    from server.runtime.ratelimit import TokenBucket
    from server.sessions.backlog import Backlog

log = logging.getLogger("motiond.session")
STATUS_BURST = 5


class Outbox(BoundedQueue[bytes]):
    """What one line-protocol client is sent, bounded in bytes, drained as one chunk.

    A transport that can write without waiting sets :attr:`write_now`: what is queued is then
    written at once by :meth:`flush` (the session flushes after the lines of a read, so their
    replies leave in one write, in the same loop turn), or in the next loop turn for what
    nobody flushes; only when ``write_now`` declines (the client is behind: the transport
    still holds unsent bytes) does the writer task drain it, in order, as without it."""

    write_now: Callable[[bytes], bool] | None = None  # True: written; False: not now
    _flush_soon = False  # a flush is due (scheduled, or promised by whoever called batch())

    async def get(self) -> bytes | None:
        """Everything queued so far as one chunk, or None once closed."""
        chunks = await self.get_all()
        return None if chunks is None else b"".join(chunks)

    def batch(self) -> None:
        """What is put from now on waits for the caller's :meth:`flush` (call it in a
        ``finally``), so a run of puts leaves in one write with no loop turn of its own."""
        self._flush_soon = True

    def flush(self) -> None:
        """Write what is queued now through :attr:`write_now`, else wake the writer task."""
        self._flush_soon = False
        items = self._items
        if not items:
            return
        write_now = self.write_now
        if write_now is not None and not self.overflowed and write_now(
                items[0] if len(items) == 1 else b"".join(items)):
            items.clear()
            self._size = 0
            return
        self._ready.set()

    def _wake(self) -> None:
        if self.write_now is None:
            self._ready.set()
        elif not self._flush_soon:  # once per loop turn, unless flushed before
            self._flush_soon = True
            asyncio.get_running_loop().call_soon(self.flush)


class SessionOutput:
    """Replies, status reports and pushes; see the module docstring."""

    # The session's state this part reads and writes (set by Session.__init__).
    kernel: Kernel
    name: str
    protocol: LineProtocol
    outbox: Outbox
    may_observe: bool
    _closing: bool
    _epoch: int
    _queued_bytes: int
    _backlog: Backlog
    _scheduler: StatusScheduler
    _status_bucket: TokenBucket
    _status_timer: asyncio.TimerHandle | None
    _replies: deque[tuple[int, asyncio.Future[bytes]]]
    _replies_room: asyncio.Event

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

    # -- pushes and replies -----------------------------------------------------------------
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
