"""One client connection, whatever the transport: protocol in, dispatcher, replies out.

A transport creates a :class:`Session`, feeds it bytes (or WebSocket text) and drains its
:class:`~server.sessions.output.Outbox`. The session has three parts on one state:

* its input, :class:`~server.sessions.input.LineAdmission`: realtime bytes acted on at
  once (``M112`` the moment its line arrives), complete lines queued (bounded), bytes beyond
  that held in a bounded backlog whose realtime bytes still act at once;
* this module: its lifecycle, logging in, and the executor, which runs the queued lines one at
  a time through the dispatcher: in the read that brought them while none waits (their
  replies leave in one write), else in its own task;
* its output, :class:`~server.sessions.output.SessionOutput`: exactly one ``ok`` or
  ``error:N`` per line, in order (deferred replies included), rate-limited status reports,
  pushes, all bounded.

A client whose address is in ``[protocol] trusted_clients`` controls without the token (senders
that cannot log in). Logging in: ``$AUTH=token`` (see :mod:`server.sessions.login_guard`:
constant-time comparison, wrong tokens answered ever later per client address, the connection
closed after ``auth_failures_per_connection``). An observer never logs in. A session on
probation (it got a TCP slot reserved for logged-in connections) must log in with its first
line.

A RepRap host (the REPRAP dialect) is kept informed while a line's ``ok`` is held (``M400``
waiting for motion, a full planner): ``echo:busy: processing`` every :data:`BUSY_INTERVAL_S`
(``M113 S<seconds>`` changes it for the connection, 0 stops it), as Marlin's host keep-alive,
so OctoPrint does not declare a communication timeout. Its lines
never raise the soft-limit alarm: a target outside the travel is refused for that line only.

A client that stops reading overflows its outbox and is disconnected, never slowing motion or
other clients. :meth:`Session.end` says why in a ``[MSG:]`` line, then the transport hangs up
once that is sent.
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

from server.config import trusted_client
from server.errors import Alarm, CommandError, Error
from server.protocol.events import Dialect, LineReceived, LineRejected
from server.protocol.http_sniff import HttpSniffer
from server.protocol.lines import LineProtocol
from server.protocol.reports import StatusScheduler
from server.runtime.events import Event as BusEvent
from server.runtime.ratelimit import (
    REALTIME_BURST_BYTES,
    TokenBucket,
    input_budget,
    realtime_allowance,
)
from server.sessions.backlog import Backlog
from server.sessions.input import INBOUND_LINES, LineAdmission, line_size
from server.sessions.login_guard import LoginGuard, token_matches
from server.sessions.output import STATUS_BURST, Outbox, SessionOutput

if TYPE_CHECKING:
    from collections.abc import Awaitable
    from typing import TypeAlias

    from server.kernel.kernel import Kernel

    # a line's reply (a future: answered downstream later), or the wait for it
    Reply: TypeAlias = bytes | asyncio.Future[bytes] | Awaitable[bytes | asyncio.Future[bytes]]
    # a line begun that must wait: the line, its connection's epoch, the wait for its reply
    Waiting: TypeAlias = tuple[
        LineReceived | LineRejected, int, Awaitable[bytes | asyncio.Future[bytes]]]

log = logging.getLogger("motiond.session")
_AUTH = re.compile(r"^\s*\$AUTH=(.*)$", re.I)
PROBATION_REFUSED = "this slot is reserved for logged-in connections: send $AUTH=<token> first"
YIELD_AFTER_S = 0.0003  # the executor gives other tasks a turn at least this often
# A run of lines answered at once is told as soon as its lines free this many bytes of the
# client's view of our input buffer (a quarter of Grbl's 128): a character-counting sender
# refills while the rest of its read is run, not after. Check-mode streaming of the raster
# corpus, AMD EPYC: 0.50-0.52 s at 24 to 40 bytes, 0.57-0.59 at 64, 0.60-0.63 unbounded,
# 0.66-0.68 a write per line (docs/performance.md)
EARLY_REPLY_BYTES = 32
BUSY_INTERVAL_S = 2.0  # Marlin's DEFAULT_KEEPALIVE_INTERVAL
BUSY = "echo:busy: processing"
__all__ = ["Session", "line_token", "login_guard", "token_matches"]


class Session(LineAdmission, SessionOutput):
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
        trusted = trusted_client(peer, core.protocol.trusted_clients)
        self.on_probation = must_login and self._token is not None and not trusted
        self.can_control = (self._token is None or trusted
                            or token_matches(token, self._token))
        self.may_observe = self.can_control or core.protocol.unauthenticated == "read-only"
        if observer:  # asked to only watch: status and pushes, never control
            self.can_control = False
        if self.on_probation:
            self.can_control = self.may_observe = False
        self._websocket = websocket
        self._sniffer = None if websocket else HttpSniffer()
        self.protocol = LineProtocol(
            line_limit=core.protocol.line_limit, dialect=core.protocol.dialect, websocket=websocket
        )
        self.outbox = Outbox(core.protocol.outgoing_limit_bytes)
        self._guard = guard if guard is not None else login_guard(kernel)
        self._auth_failures = 0
        self._ending: str | None = None
        self._lines: deque[tuple[int, LineReceived | LineRejected]] = deque()
        self._lines_ready = asyncio.Event()
        self._backlog = Backlog(core.protocol.backlog_bytes)
        self._input_room = asyncio.Event()
        self._input_room.set()
        self._stopping = asyncio.Event()
        self._stops = kernel.status  # the stop generation: each queued line's ticket
        self._epoch = 0  # counts the resets that dropped this connection's lines unanswered
        self._resetting = False  # this connection's own Ctrl-X is being acted on
        self._discarded = False  # the last stop dropped lines of this connection
        self._feeding = False  # a read is being fed in slices
        self._executor_idle = False  # the executor waits for lines: they may run in the read
        self._running = False  # lines are running (_run_lines): not again from inside one
        self._waiting: Waiting | None = None  # a line begun in the read, for the executor
        self._deferred: list[asyncio.Future[list[str]]] = []  # a line's answers-to-come
        self._defer = self._deferred.append
        self._begin = kernel.dispatcher.begin
        self._ok = self.protocol.reply_ok()  # (the same bytes for every plain line)
        self._host_untold = True
        self._queued_bytes = 0
        self._scheduler = StatusScheduler()
        self._status_bucket = TokenBucket(
            core.protocol.status_reports_per_s, STATUS_BURST, time.monotonic())
        self._status_timer: asyncio.TimerHandle | None = None
        self._input_budget = input_budget(core.protocol.read_only_input_bytes_per_s)
        self._realtime_budget = realtime_allowance(
            core.protocol.realtime_bytes_per_s, REALTIME_BURST_BYTES)
        self._text_cost = 0
        self._text_counting = True
        self._unsubscribe = [kernel.events.subscribe(BusEvent.PUSH, self.push),
                             kernel.events.subscribe(BusEvent.STOP, self._on_stop),
                             kernel.events.subscribe(BusEvent.RESET, self._on_reset)]
        self._task: asyncio.Task[None] | None = None
        self._replies: deque[tuple[int, asyncio.Future[bytes]]] = deque()  # behind a deferred
        self._replies_room = asyncio.Event()
        self._busy_timer: asyncio.TimerHandle | None = None
        self.busy_interval_s = BUSY_INTERVAL_S
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
        for unsubscribe in self._unsubscribe:
            unsubscribe()
        self._closing = True
        self._stopping.set()
        if self._status_timer is not None:
            self._status_timer.cancel()
            self._status_timer = None
        self._lines.clear()
        self._backlog.clear()
        self._lines_ready.set()
        self._input_room.set()
        self._replies_room.set()

    @property
    def closed(self) -> bool:
        return self.outbox.closed

    @property
    def soft_limit_alarms(self) -> bool:
        """Whether this connection's out-of-travel line alarms the machine: Grbl's ALARM:2 in
        the GRBL dialect; a RepRap host's line is refused alone (Marlin has no such alarm)."""
        return self.protocol.dialect is Dialect.GRBL

    @property
    def dwell_waits(self) -> bool:
        """Whether this connection's ``G4`` is answered only once the motion before it and
        the dwell have run: Grbl's ``mc_dwell`` syncs the buffer first, and senders use it as
        "wait until the machine is done" (CNCjs's ``%wait``). A RepRap host waits with
        ``M400``, Marlin's way; its ``G4`` is answered once queued."""
        return self.protocol.dialect is Dialect.GRBL

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
        """The queued lines in order, each to its end before the next. Lines that need no wait
        (most of a raster) run in one pass (:meth:`_run_lines`), with no task switch or future
        of their own, often already inside the read that brought them (:meth:`_lines_arrived`);
        this task takes over where a line must wait, and gives the loop a turn between passes."""
        lines, now_s = self._lines, time.monotonic  # (the loop's clock, without its frame)
        turn_s = now_s()
        try:
            while not self._closing:
                if not lines and self._waiting is None:
                    self._lines_ready.clear()
                    self._executor_idle = True
                    try:
                        await self._lines_ready.wait()
                    finally:
                        self._executor_idle = False
                    turn_s = now_s()
                    continue
                waiting, self._waiting = self._waiting, None
                if waiting is None:
                    self.outbox.batch()
                    try:
                        waiting = self._run_lines(turn_s + YIELD_AFTER_S)
                    finally:
                        self.outbox.flush()
                if waiting is not None:
                    await self._finish(*waiting)
                while len(self._replies) >= INBOUND_LINES and not self._closing:
                    self._replies_room.clear()
                    await self._replies_room.wait()
                if self._ending is not None:
                    self.end(self._ending)
                    return
                if now_s() - turn_s > YIELD_AFTER_S:  # lines that never wait must not hog
                    await asyncio.sleep(0)
                    turn_s = now_s()
        finally:  # a line begun in a read holds the dispatcher's turn: it runs to its end
            waiting, self._waiting = self._waiting, None
            if waiting is not None:
                await self._finish(*waiting)

    def _lines_arrived(self) -> None:
        """Lines were queued: run them now, in the read that brought them, when the executor
        is idle (nothing before them runs or waits), so their replies leave with no task switch,
        in one write (one each :data:`EARLY_REPLY_BYTES` of lines for a long read); else, or
        for what is left (a line that must wait, more than a turn's worth), the executor task
        is woken."""
        if (self._executor_idle and not self._lines_ready.is_set() and not self._running
                and not self._closing):  # (once woken, the executor runs what follows)
            self.outbox.batch()
            try:
                self._waiting = self._run_lines(time.monotonic() + YIELD_AFTER_S)
            finally:
                self.outbox.flush()
            if self._ending is not None and self._waiting is None:
                self.end(self._ending)
                return
            if not self._lines and self._waiting is None:
                return
        self._lines_ready.set()

    def _run_lines(self, until_s: float) -> Waiting | None:
        """Run queued lines in order while each is answered at once, until ``until_s`` (the
        loop's clock) or the reply queue is full: the line that must wait, begun (it holds the
        dispatcher's turn: the caller awaits it at once), or None. The caller batches the
        outbox (:meth:`Outbox.batch`) and flushes it after."""
        lines, replies, backlog = self._lines, self._replies, self._backlog
        now_s = time.monotonic  # the loop's clock (asyncio's loop.time(), without its frame)
        outbox = self.outbox
        put, freed = outbox.put, 0
        self._running = True
        try:
            while lines and not self._closing and self._ending is None:
                ticket, event = lines.popleft()
                epoch = self._epoch
                if backlog and len(lines) < INBOUND_LINES // 2:
                    self._refill()
                reply = self._execute(event, ticket)
                if type(reply) is bytes and not replies and epoch == self._epoch:
                    size = line_size(event)
                    queued = self._queued_bytes - size  # (_answered, inlined)
                    self._queued_bytes = queued if queued > 0 else 0
                    put(reply)
                    freed += size
                    if freed >= EARLY_REPLY_BYTES:
                        freed = 0
                        outbox.flush()  # (then batched again: the caller flushes the rest)
                        outbox.batch()
                elif isinstance(reply, (bytes, asyncio.Future)):  # (no union built per line)
                    self._answered(event, epoch, reply)
                else:
                    return event, epoch, reply
                if len(replies) >= INBOUND_LINES or now_s() > until_s:
                    break
            return None
        finally:
            self._running = False

    async def _finish(self, event: LineReceived | LineRejected, epoch: int,
                      outcome: Awaitable[bytes | asyncio.Future[bytes]]) -> None:
        """Wait for a line's reply (room in the planner, a sync request), then answer it."""
        self._arm_busy()
        try:
            reply = await outcome
        finally:
            self._disarm_busy()
        self._answered(event, epoch, reply)

    def _answered(self, event: LineReceived | LineRejected, epoch: int,
                  reply: bytes | asyncio.Future[bytes]) -> None:
        if epoch != self._epoch:  # a reset dropped it: no reply, as from Grbl
            return
        queued = self._queued_bytes - line_size(event)
        self._queued_bytes = queued if queued > 0 else 0
        if not self._replies and isinstance(reply, bytes):  # (what _answer does first)
            self.outbox.put(reply)
        else:
            self._answer(reply, epoch)

    def _arm_busy(self) -> None:
        """RepRap hosts: ``echo:busy: processing`` every 2 s while this line's ok is held."""
        interval_s = self.busy_interval_s
        if self.protocol.dialect is Dialect.REPRAP and not self._closing and interval_s > 0:
            loop = asyncio.get_running_loop()
            self._busy_timer = loop.call_later(interval_s, self._busy)

    def _busy(self) -> None:
        if not self._closing:
            self.outbox.put(self.protocol.push(BUSY))
            self._arm_busy()

    def _disarm_busy(self) -> None:
        if self._busy_timer is not None:
            self._busy_timer.cancel()
            self._busy_timer = None

    def _execute(self, event: LineReceived | LineRejected, ticket: int) -> Reply:
        """A line's reply, or the wait for it (to be awaited at once: the line holds the
        dispatcher's turn until then)."""
        if isinstance(event, LineRejected):
            return self.protocol.reply_error(event.error)
        if event.handled:  # M110: the protocol already set the line number
            return self.protocol.reply_ok()
        login = _AUTH.match(event.text) if "$" in event.text else None
        if login is not None:
            return self._login(login.group(1))
        if self.on_probation:
            self._ending = PROBATION_REFUSED
            return self._refuse("log in first")
        if not self.may_observe:
            return self._refuse("log in with $AUTH=")
        collected = self._deferred  # (one list and its append for every line: taken when used)
        try:
            outcome = self._begin(event.text, self, ticket, self._defer)
        except Exception as exc:  # noqa: BLE001 - answered (CommandError) or alarmed
            collected.clear()
            return self._failed(event, exc)
        if type(outcome) is list and not outcome and not collected:
            return self._ok
        if isinstance(outcome, list):
            deferred = collected.copy()
            collected.clear()
            return self._replied(outcome, deferred)
        # the line waits, and may defer its answer meanwhile: it keeps the list, the next
        # line gets a new one
        self._deferred = []
        self._defer = self._deferred.append
        return self._awaited(event, outcome, collected)

    async def _awaited(self, event: LineReceived, outcome: Awaitable[list[str]],
                       deferred: list[asyncio.Future[list[str]]]) -> bytes | asyncio.Future[bytes]:
        try:
            messages = await outcome
        except Exception as exc:  # noqa: BLE001 - answered (CommandError) or alarmed
            return self._failed(event, exc)
        return self._replied(messages, deferred)

    def _replied(self, messages: list[str],
                 deferred: list[asyncio.Future[list[str]]]) -> bytes | asyncio.Future[bytes]:
        if deferred:
            return self._later(messages, deferred)
        return self._reply_ok(messages)

    def _failed(self, event: LineReceived, exc: Exception) -> bytes:
        """A refused line's ``error:N``; anything unexpected alarms (and is answered)."""
        if isinstance(exc, CommandError):
            return self.protocol.reply_error(exc)
        log.error("line %r failed", event.text, exc_info=exc)
        self.kernel.alarm(Alarm.MODULE_FAILED, f"internal error on {event.text!r}: {exc!r}")
        return self.protocol.reply_error(CommandError(Error.UNSUPPORTED, "internal error"))


def line_token(kernel: Kernel) -> str | None:
    """The token line-protocol connections must present (config, else ``$MOTIOND_TOKEN``)."""
    return kernel.config.core.protocol.token or os.environ.get("MOTIOND_TOKEN") or None


def login_guard(kernel: Kernel) -> LoginGuard:
    """A guard for one transport's sessions, from ``[protocol]``."""
    config = kernel.config.core.protocol
    return LoginGuard(config.auth_delay_s, config.auth_max_delay_s)

