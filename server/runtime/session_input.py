"""A session's input: client bytes -> realtime actions now, complete lines into a bounded queue.

:class:`LineAdmission` is the part of :class:`~server.runtime.session.Session` (a base class of
it) that admits what the client sends. It:

* acts on realtime bytes at once (status, hold, resume, reset, overrides, jog cancel), even
  while lines wait for planner room, and on ``M112`` the moment its line arrives; an ``M410``
  quickstop too (Marlin's emergency parser): motion stops, and the lines this connection queued
  ahead of it are answered as flushed (``error:45``, one reply each) instead of running;
* queues complete lines, at most :data:`INBOUND_LINES` of them, for the session's executor;
* keeps taking bytes while its line queue is full: they wait in a
  :class:`~server.runtime.backlog.Backlog` (``[protocol] backlog_bytes``) whose realtime bytes
  are acted on as they arrive, so a sender that streams ahead without character counting can
  still hold (``!``) or reset (Ctrl-X) at once. Byte transports stop reading only while the
  backlog is full (:meth:`~LineAdmission.wait_input_room`). WebSocket messages (whose end ends
  a line) are never held back: that transport stops reading while the line queue is full
  (:meth:`~LineAdmission.wait_room`).

Its state is the session's, created by ``Session.__init__``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from server.errors import CommandError, Error
from server.protocol.events import (
    Event,
    LineReceived,
    LineRejected,
    Realtime,
    RealtimeReceived,
)
from server.runtime.control import halts_at_once, quickstops_at_once

if TYPE_CHECKING:
    import asyncio
    from collections import deque

    from server.protocol.lines import LineProtocol
    from server.protocol.reports import StatusScheduler
    from server.runtime.backlog import Backlog
    from server.runtime.kernel import Kernel
    from server.runtime.session_output import Outbox

INBOUND_LINES = 64
REFILL_BYTES = 1024  # held-back input is fed to the protocol in slices of this size


class LineAdmission:
    """Realtime bytes acted on, lines queued; see the module docstring."""

    # The session's state this part reads and writes (set by Session.__init__).
    kernel: Kernel
    protocol: LineProtocol
    outbox: Outbox
    can_control: bool
    may_observe: bool
    _websocket: bool
    _lines: deque[tuple[int, LineReceived | LineRejected]]
    _lines_ready: asyncio.Event
    _room: asyncio.Event
    _backlog: Backlog
    _input_room: asyncio.Event
    _epoch: int
    _queued_bytes: int
    _scheduler: StatusScheduler

    if TYPE_CHECKING:
        def _request_status(self) -> None: ...  # the session's output

    @property
    def backlog_full(self) -> bool:
        """Input is held back up to its bound: the transport should stop reading."""
        return not self._input_room.is_set()

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
            if not replayed and self._is_quickstop(event):
                self._quickstop()
            self._lines.append((self._epoch, event))
            self._queued_bytes += line_size(event)
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

    def _is_quickstop(self, event: Event) -> bool:
        return (isinstance(event, LineReceived) and self.can_control
                and quickstops_at_once(event.text))

    def _quickstop(self) -> None:
        """M410 arrived: stop now; the lines queued ahead of it are answered, never run."""
        flushed = LineRejected(CommandError(Error.BUSY, "flushed by an M410 quickstop; not run"))
        for index, (epoch, line) in enumerate(self._lines):
            if isinstance(line, LineReceived):
                self._lines[index] = (epoch, flushed)
                self._queued_bytes -= line_size(line) - line_size(flushed)
        self.kernel.control.quickstop()

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


def line_size(event: LineReceived | LineRejected) -> int:
    """Bytes a line took in the client's view of our input buffer (newline included)."""
    return len(event.text) + 1 if isinstance(event, LineReceived) else 1
