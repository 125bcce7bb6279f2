"""A session's input: client bytes -> realtime actions now, complete lines into a bounded queue.

:class:`LineAdmission` is the part of :class:`~server.sessions.session.Session` (a base class of
it) that admits what the client sends. It:

* closes a byte stream that starts as an HTTP request (:mod:`server.protocol.http_sniff`)
  before any of its bytes is acted on: a web page cannot drive the machine through the port;
* paces what a connection that may not control sends (:meth:`LineAdmission.pace_input`);
* bounds what realtime bytes cost, from every connection, controlling ones too
  (:meth:`LineAdmission.feed`): at most :data:`SLICE_COST` of them are examined in one
  loop turn, each connection may examine
  ``[protocol] realtime_bytes_per_s`` of them and all flooding connections together
  ``realtime_total_bytes_per_s`` (a connection within its own budget, such as the operator's
  ``!``, never waits for the others'); what arrives beyond that waits unread. A batch of
  realtime bytes acts as Grbl's realtime flags do: a command that repeats the state (a second
  ``!`` while held, an override at its limit) costs nearly nothing, a hold acts on its first
  byte, toggles and override steps are folded into one change (:mod:`server.kernel.control`);
* acts on realtime bytes at once (status, hold, resume, reset, overrides, jog cancel), even
  while lines wait for planner room, and on ``M112`` the moment its line arrives; an ``M410``
  quickstop too (Marlin's emergency parser): each is a stop (:mod:`server.runtime.state`);
* on any stop, from any path, drops what this connection sent before it: its queued lines are
  refused where they would start (``error:45``, their ticket is void), its backlog and
  partial line go at once; a reset drops its queued lines unanswered, then the banner, as
  Grbl empties its receive buffer, and with them what followed the Ctrl-X in the same read;
* queues complete lines, at most :data:`INBOUND_LINES` of them, for the session's executor;
* keeps taking bytes while its line queue is full: they wait in a
  :class:`~server.sessions.backlog.Backlog` (``[protocol] backlog_bytes``) whose realtime bytes
  are acted on as they arrive, so a sender that streams ahead without character counting can
  still hold (``!``) or reset (Ctrl-X) at once. This is the one realtime path of every
  transport: TCP, serial, pty and WebSocket messages (held with their ends, which end lines).
  A transport stops reading only while the backlog is full
  (:meth:`~LineAdmission.wait_input_room`).

Its state is the session's, created by ``Session.__init__``.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from server.kernel.control import MAY_STOP_AT_ONCE, halts_at_once, quickstops_at_once
from server.protocol.events import (
    Dialect,
    Event,
    LineReceived,
    LineRejected,
    Realtime,
    RealtimeReceived,
)
from server.protocol.http_sniff import HttpSniffer
from server.runtime.events import MachineState
from server.runtime.ratelimit import Allowance, TokenBucket

if TYPE_CHECKING:
    from collections import deque

    from server.kernel.kernel import Kernel
    from server.protocol.lines import LineProtocol
    from server.protocol.reports import StatusScheduler
    from server.runtime.state import MachineStatus
    from server.sessions.backlog import Backlog
    from server.sessions.output import Outbox

log = logging.getLogger("motiond.session")
HTTP_REFUSED = "this port speaks the Grbl line protocol, not HTTP: closing"
READ_ONLY_CHUNK = 256  # bytes of a connection that may not control examined at a time
INBOUND_LINES = 64
SLICE_COST = 32  # realtime bytes examined in one loop turn at most (a few hundred us)
RESET_COST = 8  # a Ctrl-X costs as much as this many other realtime bytes (banner, reset)
_STATUS_RUN = re.compile(rb"\?{2,}")
_NOT_REALTIME = bytes(b for b in range(256) if b not in b"?!~\x18" and b < 0x80)
_LOOKS_REALTIME = bytes(b for b in range(0x80) if b not in b"?!~")  # to delete: the rest does
REFILL_BYTES = 1024  # held-back input is fed to the protocol in slices of this size
READ_CHUNK = 4096  # bytes a transport reads at a time (then gives the loop a turn)


class LineAdmission:
    """Realtime bytes acted on, lines queued; see the module docstring."""

    # The session's state this part reads and writes (set by Session.__init__).
    kernel: Kernel
    name: str
    protocol: LineProtocol
    outbox: Outbox
    can_control: bool
    may_observe: bool
    _websocket: bool
    _lines: deque[tuple[int, LineReceived | LineRejected]]
    _lines_ready: asyncio.Event
    _backlog: Backlog
    _input_room: asyncio.Event
    _stops: MachineStatus
    _epoch: int
    _resetting: bool
    _closing: bool
    _discarded: bool  # the last stop dropped something this connection sent
    _feeding: bool  # a read is being fed in slices (feed)
    _host_untold: bool  # a RepRap host, once recognised, is told of an alarm in force
    _replies: deque[tuple[int, asyncio.Future[bytes]]]
    _queued_bytes: int
    _scheduler: StatusScheduler
    _sniffer: HttpSniffer | None
    _input_budget: TokenBucket
    _realtime_budget: Allowance
    _text_cost: int  # of the bytes just examined, those in complete lines (text, not realtime)
    _text_counting: bool  # whether to count them (not when those bytes cost nothing anyway)

    if TYPE_CHECKING:
        def _request_status(self) -> None: ...  # the session's output
        def push(self, message: str) -> None: ...  # the session's output
        def end(self, reason: str) -> None: ...  # the session's lifecycle
        def _lines_arrived(self) -> None: ...  # the session's executor: run them

    @property
    def backlog_full(self) -> bool:
        """Input is held back up to its bound: the transport should stop reading."""
        return not self._input_room.is_set()

    def receive_data(self, data: bytes, *, final: bool = True) -> None:
        """Bytes from the client: a byte stream's next bytes (TCP, serial, pty), or part of a
        WebSocket message (text frames UTF-8 encoded; ``final``: its last part, whose end ends
        its last line). Realtime bytes are acted on now, whatever is queued in front of them.

        A byte stream that starts with an HTTP request line (a web page ``fetch()``-ing the
        port) ends the session before any of it is acted on."""
        if self._sniffer is not None:
            data = self._sniffer.feed(data)
            if self._sniffer.http:
                self._stop_http()
                return
            if self._sniffer.decided:
                self._sniffer = None
        final = final and self._websocket
        while data:
            if not (self._backlog or len(self._lines) >= INBOUND_LINES):
                self._handle(self.protocol.receive_data(data, final=final))
                return
            reset_at = data.find(b"\x18") if self.can_control else -1
            if reset_at < 0:
                self._hold_back(data, final)
                return
            self._hold_back(data[:reset_at], False)
            self._realtime(Realtime.RESET)  # drops what is held, as Grbl empties its buffer
            return  # and what came right behind the Ctrl-X, as Grbl's reset flushes it

    async def feed(self, data: bytes, *, final: bool = True,
                   gone: Callable[[], bool] | None = None) -> None:
        """What a transport read, handed over: the one input path of every transport (TCP,
        serial, pty, WebSocket messages, ``final`` on a message's last part). Paced as
        :meth:`pace_input` and the realtime budget say, in slices of at most
        :data:`SLICE_COST` bytes the protocol reads one by one, with a loop turn between them,
        waiting while the backlog is full. What such bytes turn out to be inside complete lines
        (UTF-8 text) is not charged to the realtime budget. ``gone()`` says the client has
        hung up: what of a flood it had sent is not examined yet is then dropped, so its
        realtime bytes never act late, after it left (a ``~`` after the operator's ``!``).
        A reset while the read is fed (its own Ctrl-X, or another's) drops the rest of it:
        those bytes came before the reset, as the ones Grbl flushes from its buffer."""
        epoch = self._epoch
        try:
            await self._feed_slices(data, final, gone, epoch)
        finally:
            self._feeding = False

    async def _feed_slices(self, data: bytes, final: bool, gone: Callable[[], bool] | None,
                           epoch: int) -> None:
        first = True
        while True:
            if not first and gone is not None and gone():
                return
            first = False
            cost = realtime_cost(data)
            if cost <= SLICE_COST:  # (the common read: no slicing, counted once)
                piece, data = data, b""
            else:
                size = affordable(data, SLICE_COST)
                piece, data = data[:size], data[size:]
                cost = realtime_cost(piece)
            self._feeding = bool(data)  # more of this read waits behind this slice
            if not self.can_control:
                await self.pace_input(len(piece))
            if self._realtime_wait_s() > 0.0:
                await self._pace_realtime()
            if self.outbox.closed or self._epoch != epoch:  # (a reset: the rest came before it)
                return
            self._text_cost = 0
            self._text_counting = cost > 0  # nothing to refund: no line's text is looked at
            try:
                self.receive_data(piece, final=final and not data)
            finally:
                self._text_counting = True
            self._spend_realtime(max(0, cost - self._text_cost))
            if not self._input_room.is_set():
                await self.wait_input_room()
            if not data:
                return
            await asyncio.sleep(0)  # a large read must not hold the loop: one slice a turn

    async def _pace_realtime(self) -> None:
        """Wait as long as :meth:`_realtime_wait_s` says."""
        while True:
            wait_s = self._realtime_wait_s()
            if wait_s <= 0.0:
                return
            await asyncio.sleep(wait_s)

    def _realtime_wait_s(self) -> float:
        """How long to wait before examining more: while this connection has spent its
        realtime budget, or, flooding, while all flooding connections have spent theirs
        together. A connection within half its own budget never waits for the others: the
        operator's ``!`` acts at once. 0 once the session has ended."""
        if self.outbox.closed:
            return 0.0
        now_s = time.monotonic()
        wait_s = self._realtime_budget.wait_s(now_s)
        if self._realtime_budget.level(now_s) < self._realtime_budget.burst / 2:
            wait_s = max(wait_s, self.kernel.realtime_input.wait_s(now_s))
        return wait_s

    def _spend_realtime(self, cost: int) -> None:
        if cost:
            now_s = time.monotonic()
            self._realtime_budget.spend(now_s, cost)
            self.kernel.realtime_input.spend(now_s, cost)

    @property
    def read_size(self) -> int:
        """How many bytes a transport should read (and feed) at a time."""
        return READ_CHUNK if self.can_control else READ_ONLY_CHUNK

    async def pace_input(self, size_bytes: int) -> None:
        """Wait until ``size_bytes`` more may be examined. A connection that may not control
        gets ``[protocol] read_only_input_bytes_per_s``, and all of them together
        ``read_only_input_total_bytes_per_s``: their bytes (realtime ones too: a flood of
        ``!`` or ``0x91``) cost a bounded share of the loop whatever their number; what they
        send beyond that waits unread (the transport's buffers fill, then the client's)."""
        total = self.kernel.read_only_input
        while not self.can_control and not self.outbox.closed:
            now_s = time.monotonic()
            wait_s = max(self._input_budget.wait_s(now_s, size_bytes),
                         total.wait_s(now_s, size_bytes))
            if wait_s == 0.0:
                self._input_budget.take(now_s, size_bytes)
                total.take(now_s, size_bytes)
                return
            await asyncio.sleep(wait_s)

    def _stop_http(self) -> None:
        if not self.outbox.closed:
            log.warning("%s: an HTTP request on the line protocol port (a web page?): closed",
                        self.name)
            self.end(HTTP_REFUSED)

    async def wait_input_room(self) -> None:
        """Wait while the backlog is full (a byte transport stops reading meanwhile)."""
        await self._input_room.wait()

    def _hold_back(self, data: bytes, final: bool) -> None:
        """The line queue is full: keep the bytes, act on their realtime commands now."""
        batch: list[Realtime] = []
        for event in self._backlog.hold(self.protocol, data, final, keep=seen_ahead):
            if isinstance(event, RealtimeReceived):
                batch.append(event.command)
                continue
            self._count_text(event)
            if self._is_emergency_stop(event) or self._is_quickstop(event):
                self._act_on_realtime(batch)  # in stream order with the stop
                if self._is_emergency_stop(event):
                    self.kernel.control.emergency_stop()
                else:
                    self.kernel.control.quickstop()
        self._act_on_realtime(batch)
        if self._backlog.full:
            self._input_room.clear()

    def _handle(self, events: list[Event], *, replayed: bool = False) -> None:
        """Protocol events in stream order; ``replayed``: from held-back bytes, whose realtime
        commands and M112 were acted on when they arrived. Realtime commands are acted on as
        one batch (see ``MachineControl.realtime_batch``), cut where order matters: at an
        M112 or an M410, and at a Ctrl-X, which ends the read: what came right behind it in
        the same read is dropped with what was queued, as Grbl's reset flushes its buffer.
        Each line is queued with its ticket: the stop generation it arrived in."""
        batch: list[Realtime] = []
        stops = self._stops
        for event in events:
            if isinstance(event, RealtimeReceived):
                if not replayed:
                    batch.append(event.command)
                    if event.command is Realtime.RESET and self.can_control:
                        self._act_on_realtime(batch)
                        self._lines_ready.set()
                        return
                continue
            if not replayed and self._text_counting:
                self._count_text(event)
            # (an M112 or M410 holds its number's digits: most lines are not looked at)
            if not replayed and ("112" in event.text or "410" in event.text):
                if self._is_emergency_stop(event):
                    self._act_on_realtime(batch)
                    self.kernel.control.emergency_stop()
                if self._is_quickstop(event):
                    self._act_on_realtime(batch)
                    self.kernel.control.quickstop()
            self._lines.append((stops.stops, event))
            self._queued_bytes += line_size(event)
        self._act_on_realtime(batch)
        if self._host_untold and self.protocol.dialect is Dialect.REPRAP:
            self._tell_host()
        if self._lines:
            self._lines_arrived()

    def _tell_host(self) -> None:
        """A RepRap host just recognised (OctoPrint connecting) learns of an alarm in force:
        the ``ALARM:N`` push, with the notification OctoPrint shows."""
        self._host_untold = False
        status = self._stops
        if status.state is MachineState.ALARM:
            self.push(f"ALARM:{status.alarm_code}")

    def _count_text(self, event: Event) -> None:
        """A line's bytes that look like realtime ones (UTF-8 text; ``!`` in a RepRap host's
        ``M117``) were text: they do not count against the realtime budget."""
        if self._text_counting and isinstance(event, LineReceived):
            self._text_cost += realtime_cost(event.text.encode("utf-8", "surrogatepass"))

    def _act_on_realtime(self, batch: list[Realtime]) -> None:
        """Act on the realtime commands gathered so far (then forget them): the others
        folded, then one status report however many ``?`` (like Grbl's status flag; it shows
        a hold sent with it), a Ctrl-X (only ever last) after them."""
        if not batch:
            return
        others = [command for command in batch
                  if command is not Realtime.STATUS and command is not Realtime.RESET]
        if others and self.may_observe and self.can_control:
            self.kernel.control.realtime_batch(others)
        if Realtime.STATUS in batch:
            self._realtime(Realtime.STATUS)
        if batch[-1] is Realtime.RESET:
            self._realtime(Realtime.RESET)
        batch.clear()

    def _is_emergency_stop(self, event: Event) -> bool:
        """M112 from a connection that may control, acted on the moment its line arrives:
        whatever its checksum or line number (a refused frame keeps its text), as Marlin's
        emergency parser."""
        return self.can_control and not isinstance(event, RealtimeReceived) and halts_at_once(
            event.text)

    def _is_quickstop(self, event: Event) -> bool:
        return (isinstance(event, LineReceived) and self.can_control
                and quickstops_at_once(event.text))

    # -- stops ------------------------------------------------------------------------------
    def _on_stop(self, reason: str) -> None:
        """A stop, from this connection or any other path. The lines this connection queued
        before it carry a void ticket: each is refused where it would start (``error:45``,
        or Marlin's ``echo:`` + ``ok``), never run. What it sent that is not a line yet (the
        backlog, a partial line) is dropped now; a reset drops the rest (:meth:`_on_reset`).
        A read-only connection's queries are not requests: they stay."""
        if self._closing or not self.can_control:
            return
        self._discarded = bool(self._queued_bytes or self._backlog or self._replies
                               or self._feeding)
        self._backlog.clear()
        self._input_room.set()
        self.protocol.reset()
        self._scheduler.refresh()

    def _on_reset(self) -> None:
        """A reset (this connection's Ctrl-X, another's, ``machine.reset``, a restart): as
        Grbl empties its receive buffer, the lines this connection sent are dropped with no
        reply, and the banner tells the sender to count from nothing again, for its own
        Ctrl-X always, else when the reset dropped something of a Grbl sender's (a RepRap
        host, which waits for one reply per line, gets its lines refused instead)."""
        own, self._resetting = self._resetting, False
        dropped, self._discarded = self._discarded or self._feeding, False
        if self._closing or not (own or (dropped and self.protocol.dialect is Dialect.GRBL)):
            return
        self._epoch += 1
        self._lines.clear()
        self._queued_bytes = 0
        if not self.outbox.closed:
            self.outbox.put(self.protocol.banner())

    def _refill(self) -> None:
        """Feed held-back bytes to the protocol until the line queue is full again."""
        while self._backlog and len(self._lines) < INBOUND_LINES:
            piece, final = self._backlog.take(REFILL_BYTES)
            self._handle(self.protocol.receive_data(piece, final=final), replayed=True)
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
        if command is Realtime.RESET:  # a stop: _on_stop and _on_reset drop what was sent
            self._resetting = True
            self.kernel.control.reset()
            if self._resetting:  # (a machine that emitted no reset event)
                self._on_reset()
            return
        self.kernel.control.realtime(command)


def realtime_cost(data: bytes) -> int:
    """What examining ``data`` costs in realtime bytes: the bytes the protocol may take one
    at a time (``?`` ``!`` ``~``, Ctrl-X, bytes above 0x7F; a run of ``?`` is taken at once),
    a Ctrl-X :data:`RESET_COST`. Counted in C, without examining them one by one."""
    data = _STATUS_RUN.sub(b"?", data) if b"??" in data else data  # a run is read at once
    return len(data.translate(None, _NOT_REALTIME)) + (RESET_COST - 1) * data.count(0x18)


def affordable(data: bytes, cost_limit: int) -> int:
    """The length of the longest start of ``data`` whose :func:`realtime_cost` is at most
    ``cost_limit`` (at least one byte): a bisection of C-speed counts."""
    if realtime_cost(data) <= cost_limit:
        return len(data)
    low, high = 1, len(data)  # data[:high] costs too much; data[:low] is the least we take
    while high - low > 1:
        middle = (low + high) // 2
        if realtime_cost(data[:middle]) <= cost_limit:
            low = middle
        else:
            high = middle
    return low


def seen_ahead(lines: bytes) -> bool:
    """Whether held-back ``lines`` must be looked at when they arrive: one may be an M112 or
    M410, or hold bytes that look like realtime ones (text: not charged to the realtime
    budget). The others wait unread until the protocol itself reads them."""
    if lines.translate(None, _LOOKS_REALTIME):
        return True
    if (b"112" not in lines and b"410" not in lines) or (b"M" not in lines and b"m" not in lines):
        return False  # (faster than the search below, which decides)
    return MAY_STOP_AT_ONCE.search(lines) is not None


def line_size(event: LineReceived | LineRejected) -> int:
    """Bytes a line took in the client's view of our input buffer (newline included)."""
    return len(event.text) + 1 if isinstance(event, LineReceived) else 1
