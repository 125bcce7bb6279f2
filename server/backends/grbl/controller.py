"""The asyncio side of a Grbl controller connection: open, handshake, stream, poll, reconnect.

:class:`Controller` owns one task (:meth:`Controller.run`). It opens the device (a serial port
or a pseudo-terminal with pyserial-asyncio, or ``host:port`` with asyncio streams), waits for
the welcome banner (opening an Arduino's port resets it: the banner comes once its bootloader
has run; a controller that stays silent gets a Ctrl-X), asks ``$I``, ``$$``, ``$#`` and ``$G``,
reports them to its listener, then polls ``?`` at ``status_hz`` and reads until the connection
is lost. A lost connection drops every unanswered line (their futures raise
:class:`LineDropped`), tells the listener, and is retried every ``reconnect_s``.

Lines go through the pure :class:`~server.backends.grbl.link.Link`: :meth:`Controller.send_line`
waits for room in the controller's receive buffer, writes the line and returns a future that
resolves with the controller's :class:`~server.backends.grbl.link.Answered`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from server.backends.grbl.holdwatch import HoldWatch, Verdict
from server.backends.grbl.link import (
    DEFAULT_BUFFER_BYTES,
    AlarmReport,
    Answered,
    Banner,
    Feedback,
    Link,
    LinkEvent,
    StatusReport,
    parse_build_options,
    parse_settings,
)
from server.backends.grbl.reports import MAX_AXES, MAX_RX_BYTES, ControllerStatus

if TYPE_CHECKING:
    from server.config import BackendConfig

log = logging.getLogger("motiond.grbl")
READ_BYTES = 1024  # per loop iteration: a burst from a chatty board must not hold up clients
RESET = 0x18
STATUS = 0x3F
HOLD, RESUME = 0x21, 0x7E
_STILL = frozenset({"Idle", "Alarm", "Check", "Sleep"})  # nothing moves without a command
SUMMARY_PERIOD_S = 10.0  # at most one warning this often about a noisy board
POLLS_REMEMBERED = 32  # '?' sent and not yet answered by a report (Grbl may merge some)


class LineDropped(Exception):
    """The controller will never answer this line (reset, restart or lost connection)."""


GRBLHAL_FIRMWARE = "[FIRMWARE:grblHAL]"


@dataclass(frozen=True, slots=True)
class Handshake:
    """What the controller told about itself when it connected."""

    banner: str
    build_info: tuple[str, ...]
    settings: dict[int, float]
    offsets: tuple[str, ...]
    modal: tuple[str, ...]

    @property
    def grblhal(self) -> bool:
        """The board is grblHAL (its ``$I`` says ``[FIRMWARE:grblHAL]``)."""
        return GRBLHAL_FIRMWARE in self.build_info

    @property
    def axis_count(self) -> int | None:
        """The board's axes: the values of its ``[G54:x,y,z]`` (None if it printed none)."""
        for text in self.offsets:
            if text.startswith("[G54:") and text.endswith("]"):
                count = text.count(",") + 1
                return count if count <= MAX_AXES else None
        return None


class ControllerListener(Protocol):
    """What the controller tells its owner (all called from the event loop)."""

    def on_connected(self, handshake: Handshake) -> None: ...

    def on_status(self, status: ControllerStatus) -> None: ...

    def on_answer(self) -> None: ...

    def on_alarm(self, code: int) -> None: ...

    def on_feedback(self, texts: list[str]) -> None: ...

    def on_lost(self, reason: str) -> None: ...

    def on_restart(self, banner: str) -> None: ...

    def on_requeried(self, modal: tuple[str, ...], offsets: tuple[str, ...]) -> None: ...


class Controller:
    """One downstream controller; see the module docstring."""

    def __init__(self, config: BackendConfig, listener: ControllerListener) -> None:
        self.config = config
        self.listener = listener
        self.link = Link(config.buffer_bytes or DEFAULT_BUFFER_BYTES)
        self.status: ControllerStatus | None = None
        self.ready = False  # handshake done: client lines may flow
        self.handshake: Handshake | None = None
        self.lines_sent = 0
        self.status_polls = 0  # '?' sent to the board: one task, whatever the clients ask
        self._writer: asyncio.StreamWriter | None = None
        self._futures: dict[int, asyncio.Future[Answered]] = {}
        self._room = asyncio.Event()
        self._banner = asyncio.Event()
        self._banner_text = ""
        self._reset_sent = False  # a banner after our own Ctrl-X is expected
        self._banner_watch: asyncio.TimerHandle | None = None
        self._buffer_from_report = config.buffer_bytes is None
        self._rx_bytes_cap = MAX_RX_BYTES  # $I's [OPT:...,bytes] - 1, once known
        self._rx_seen: int | None = None  # a Bf: figure waiting for its confirmation
        self._heard_s = 0.0  # loop time of the last report or answer
        self.motion_pending = False  # a motion line sent, not yet seen completed by the board
        self._motion_lines = 0  # motion lines sent on this connection (a generation count)
        self._polls: deque[tuple[int, bool]] = deque(maxlen=POLLS_REMEMBERED)
        self._hold = HoldWatch()  # a '!' the board has not yet been seen to take
        # After a reset the board runs its start-up lines ($N0, $N1): its modes and offsets are
        # asked again before any other line (clear while they are being asked).
        self.requeried = asyncio.Event()
        self.requeried.set()

    @property
    def where(self) -> str:
        return self.config.serial or self.config.tcp or "?"

    # -- the task ---------------------------------------------------------------------------
    async def run(self) -> None:
        """Connect, serve, and reconnect forever (until cancelled)."""
        failures = 0
        try:
            while True:
                try:
                    reader, writer = await self._open()
                except (OSError, ValueError) as exc:
                    if failures == 0:
                        log.warning("cannot open the controller at %s (%s); retrying every "
                                    "%.1f s", self.where, exc, self.config.reconnect_s)
                    failures += 1
                    await asyncio.sleep(self.config.reconnect_s)
                    continue
                failures = 0
                reason = await self._serve(reader, writer)
                self._drop_connection(reason)
                await asyncio.sleep(self.config.reconnect_s)
        finally:
            self._drop_connection("motiond is stopping", tell=False)

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        if self.config.tcp is not None:
            host, _, port = self.config.tcp.rpartition(":")
            return await asyncio.open_connection(host, int(port))
        import serial_asyncio_fast as serial_asyncio  # pyserial-asyncio-fast

        assert self.config.serial is not None
        reader, writer = await serial_asyncio.open_serial_connection(
            url=self.config.serial, baudrate=self.config.baud)
        return reader, writer

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> str:
        """Handshake and poll beside the reader; returns why the connection ended."""
        self._writer = writer
        self._banner.clear()
        self.link.lost()
        if self.config.buffer_bytes is None:  # the board's figure is learnt again
            self.link.buffer_bytes = DEFAULT_BUFFER_BYTES
            self._buffer_from_report, self._rx_seen = True, None
        reading = asyncio.create_task(self._read(reader), name="grbl-read")
        talking = asyncio.create_task(self._talk(), name="grbl-talk")
        try:
            done, _ = await asyncio.wait({reading, talking}, return_when=asyncio.FIRST_COMPLETED)
            finished = done.pop()
            return finished.result() if not finished.cancelled() else "cancelled"
        except Exception as exc:  # noqa: BLE001 - any failure ends this connection only
            return f"{type(exc).__name__}: {exc}"
        finally:
            for task in (reading, talking):
                task.cancel()
            await asyncio.gather(reading, talking, return_exceptions=True)

    async def _read(self, reader: asyncio.StreamReader) -> str:
        while True:
            try:
                data = await reader.read(READ_BYTES)
            except OSError as exc:
                return f"read failed: {exc}"
            if not data:
                return "the controller closed the connection"
            feedback: list[str] = []  # lines answering nothing, told in one call, in order
            for event in self.link.receive(data):
                if isinstance(event, Feedback):
                    feedback.append(event.text)
                    continue
                if feedback:
                    self._feedback(feedback)
                    feedback = []
                self._event(event)
            if feedback:
                self._feedback(feedback)
            await asyncio.sleep(0)  # a burst is read without suspending: let clients' '?' in

    def _feedback(self, texts: list[str]) -> None:
        if self.ready:
            self.listener.on_feedback(texts)
        else:  # a bootloader's noise, the start-up messages: nothing for the clients
            log.debug("controller at %s, before the handshake: %d lines, first %r", self.where,
                      len(texts), texts[0])

    async def _talk(self) -> str:
        """Banner, start-up queries, then status polling until the connection ends."""
        banner = await self._wait_banner()
        replies = []
        for query in ("$I", "$$", "$#", "$G"):
            answer = await asyncio.wait_for(await self._send(query), self.config.reply_timeout_s)
            replies.append(answer.messages if answer.error is None else ())
            if query == "$I" and GRBLHAL_FIRMWARE in replies[0]:
                self.link.use_grblhal()
        self.handshake = Handshake(banner, replies[0], parse_settings(replies[1]), replies[2],
                                   replies[3])
        options = parse_build_options(replies[0])
        self._rx_bytes_cap = options[1] - 1 if options else MAX_RX_BYTES
        self.ready = True
        self._room.set()
        log.info("controller at %s: %s", self.where, banner)
        self.listener.on_connected(self.handshake)
        return await self._poll_while_answering()

    async def _poll_while_answering(self) -> str:
        """Poll ``?`` at ``status_hz``; a board silent for ``silent_timeout_s`` (hung, or its
        USB chip alive and its MCU not) gets Ctrl-X, which stops it and turns its tools off if
        it still listens, and the connection ends (ALARM:42, then a reconnect)."""
        loop = asyncio.get_running_loop()
        period_s = 1.0 / self.config.status_hz
        self._heard_s = summary_s = loop.time()
        counts = (self.link.garbled_reports, self.link.dropped_lines)
        while True:
            self.poll()
            await asyncio.sleep(period_s)
            if loop.time() - summary_s >= SUMMARY_PERIOD_S:
                summary_s, counts = loop.time(), self._summarise(counts)
            silent_s = loop.time() - self._heard_s
            if silent_s > self.config.silent_timeout_s:
                if self._writer is not None:
                    self._writer.write(bytes((RESET,)))
                return f"the controller is not answering (silent for {silent_s:.1f} s)"

    def _summarise(self, before: tuple[int, int]) -> tuple[int, int]:
        """One warning for what the board sent that was dropped since ``before``."""
        now = (self.link.garbled_reports, self.link.dropped_lines)
        if now != before:
            log.warning("controller at %s: %d status reports did not parse and %d lines were "
                        "dropped (too long, or too many) in the last %.0f s", self.where,
                        now[0] - before[0], now[1] - before[1], SUMMARY_PERIOD_S)
        return now

    def poll(self) -> None:
        """Send ``?``, remembering whether every line sent so far had been answered: only a
        report to such a poll can say that the board finished the motion it was sent (Grbl
        starts a cycle once its input is empty, before it reads the next ``?``)."""
        if self._writer is None:
            return
        self._polls.append((self._motion_lines, self.link.in_flight == 0))
        self.realtime(STATUS)
        self.status_polls += 1

    async def _wait_banner(self) -> str:
        try:
            await asyncio.wait_for(self._banner.wait(), self.config.banner_timeout_s)
        except TimeoutError:
            log.info("no banner from %s: sending Ctrl-X", self.where)
            self.reset()
            await asyncio.wait_for(self._banner.wait(), self.config.reply_timeout_s)
        return self._banner_text

    # -- events from the controller ---------------------------------------------------------
    def _event(self, event: LinkEvent) -> None:
        self._heard_s = asyncio.get_running_loop().time()  # (a chatty board is not: Feedback)
        if isinstance(event, Answered):
            future = self._futures.pop(event.token, None)
            if future is not None and not future.done():
                future.set_result(event)
            self._room.set()
            self.listener.on_answer()
        elif isinstance(event, StatusReport):
            self._status(event.status)
        elif isinstance(event, AlarmReport):
            self.listener.on_alarm(event.code)
        elif isinstance(event, Banner):
            self._fail(event.dropped, "the controller restarted")
            self._forget_motion()
            self._banner_text = event.text
            expected, self._reset_sent = self._reset_sent, False
            self._stop_banner_watch()
            self._banner.set()
            if self.ready and not expected:  # reset button, power, a DTR pulse
                self.listener.on_restart(event.text)
            if not self.link.awaiting_banner:  # (not reset again meanwhile)
                if self.ready:
                    self._requery()
                else:
                    self.requeried.set()  # the handshake asks them
            self._room.set()

    def _status(self, status: ControllerStatus) -> None:
        self.status = status
        poll = self._polls.popleft() if self._polls else None
        self._watch_hold(status.base_state)
        if (status.base_state in _STILL and poll == (self._motion_lines, True)
                and self.link.in_flight == 0):
            self.motion_pending = False
        self._adopt_buffer(status)
        self.listener.on_status(status)

    def _watch_hold(self, state: str) -> None:
        """A hold the board did not take is sent again (:mod:`.holdwatch`)."""
        verdict = self._hold.report(state, self.status_polls - len(self._polls))
        if verdict is Verdict.RESEND:
            log.warning("controller at %s still runs after '!': sent again", self.where)
            if self._writer is not None:
                self._writer.write(bytes((HOLD,)))
            self._hold.asked(self.status_polls, again=True)
        elif verdict is Verdict.GIVE_UP:
            log.error("controller at %s does not hold: '!' sent %d times", self.where,
                      self._hold.resends)

    def _adopt_buffer(self, status: ControllerStatus) -> None:
        """The receive buffer from ``Bf:`` (free bytes while idle with nothing in flight): the
        same figure in two reports in a row, at most what ``$I`` says, adopted once per
        connection and never grown after (one noisy report must not overflow the board)."""
        if not self._buffer_from_report:
            return
        idle = status.base_state == "Idle" and self.link.in_flight == 0
        seen = status.rx_free_bytes if idle and status.rx_free_bytes else None
        confirmed, self._rx_seen = seen is not None and seen == self._rx_seen, seen
        if confirmed and seen is not None:
            self.link.buffer_bytes = max(16, min(seen, self._rx_bytes_cap))
            self._buffer_from_report = False
            log.info("controller receive buffer: %d bytes (from Bf:)", self.link.buffer_bytes)

    def _requery(self) -> None:
        """``$G`` and ``$#`` right after the banner, ahead of any other line: the board ran
        its start-up lines (``>G20:ok``, shown to the clients) before it reads them."""
        self.requeried.clear()
        asked = [self._write("$G"), self._write("$#")]

        def answered(_: object) -> None:
            if not all(future.done() for future in asked):
                return
            self.requeried.set()
            if any(future.cancelled() or future.exception() is not None for future in asked):
                return  # a reset or a lost connection meanwhile: asked again, or reconnected
            modal, offsets = (future.result() for future in asked)
            started = [text for text in modal.messages if text.startswith(">")]
            if started:
                self.listener.on_feedback(started)
            if modal.error is None and offsets.error is None:
                self.listener.on_requeried(
                    tuple(t for t in modal.messages if not t.startswith(">")), offsets.messages)

        for future in asked:
            future.add_done_callback(answered)

    # -- sending ----------------------------------------------------------------------------
    async def send_line(
        self, text: str, still_valid: Callable[[], bool] = lambda: True, *, motion: bool = False
    ) -> asyncio.Future[Answered]:
        """Wait for room in the controller's buffer, write ``text``; the future resolves with
        its answer. Raises :class:`LineDropped` at once while the controller is not connected,
        and if ``still_valid()`` no longer holds once there is room (a reset meanwhile).
        ``motion``: the line moves the machine, which is busy until a report says it is done."""
        while not self.ready:
            if self._writer is None:
                raise LineDropped(f"the controller at {self.where} is not connected")
            self._room.clear()
            await self._room.wait()
        future = await self._send(text, still_valid)
        if motion:
            self._motion_lines += 1
            self.motion_pending = True
        return future

    async def answered_all(self) -> None:
        """Until every line sent has been answered (or dropped by a reset or a lost
        connection): then the board's parser state is what motiond's interpreter says."""
        while self.link.in_flight and self._writer is not None:
            self._room.clear()
            await self._room.wait()

    async def _send(
        self, text: str, still_valid: Callable[[], bool] = lambda: True
    ) -> asyncio.Future[Answered]:
        size = len(text.encode("ascii", "replace")) + 1
        while not self.link.fits(size):
            if self._writer is None:
                raise LineDropped(f"the controller at {self.where} is not connected")
            self._room.clear()
            await self._room.wait()
        if self._writer is None:
            raise LineDropped(f"the controller at {self.where} is not connected")
        if not still_valid():
            raise LineDropped("motion was reset while this line waited")
        return self._write(text)

    def _write(self, text: str) -> asyncio.Future[Answered]:
        """Write a line that fits now; the future of its answer."""
        assert self._writer is not None
        token, data = self.link.send(text)
        future: asyncio.Future[Answered] = asyncio.get_running_loop().create_future()
        self._futures[token] = future
        self._writer.write(data)
        self.lines_sent += 1
        return future

    def realtime(self, byte: int) -> None:
        """A realtime byte (``?``, ``!``, ``~``, overrides...), written at once; a ``!`` is
        watched until the board holds (:mod:`.holdwatch`)."""
        if self._writer is not None:
            self._writer.write(bytes((byte,)))
        if byte == HOLD:
            self._hold.asked(self.status_polls)
        elif byte in (RESUME, RESET):
            self._hold.clear()

    def reset(self) -> None:
        """Ctrl-X: the controller stops and empties its buffer; unanswered lines are dropped."""
        if self._writer is None:
            return
        self._writer.write(bytes((RESET,)))
        self._reset_sent = True
        self.requeried.clear()  # until the board's modes after its start-up lines are known
        self._forget_motion()
        self._fail(self.link.reset(), "reset")
        if self.ready and self._banner_watch is None:
            self._banner_watch = asyncio.get_running_loop().call_later(
                self.config.reply_timeout_s, self._no_banner_after_reset)

    def _no_banner_after_reset(self) -> None:
        """A board that does not come back from Ctrl-X is hung: reconnect (which alarms), so
        lines never wait for it for ever."""
        self._banner_watch = None
        if self.link.awaiting_banner and self._writer is not None:
            log.error("no banner from %s %.1f s after Ctrl-X: reconnecting", self.where,
                      self.config.reply_timeout_s)
            self._writer.close()

    def _stop_banner_watch(self) -> None:
        if self._banner_watch is not None:
            self._banner_watch.cancel()
            self._banner_watch = None

    def _forget_motion(self) -> None:
        """A reset or a lost connection: the board's buffer is empty, earlier polls moot."""
        self.motion_pending = False
        self._polls.clear()
        self._hold.clear()

    def _fail(self, tokens: list[int] | tuple[int, ...], reason: str) -> None:
        for token in tokens:
            future = self._futures.pop(token, None)
            if future is not None and not future.done():
                future.set_exception(LineDropped(reason))
                future.exception()  # retrieved: nobody may be waiting for it any more
        self._room.set()

    def _drop_connection(self, reason: str, *, tell: bool = True) -> None:
        writer, self._writer = self._writer, None
        was_ready, self.ready = self.ready, False
        self.requeried.set()  # nothing to wait for: lines fail until the next handshake
        self._stop_banner_watch()
        self.status = None
        self._forget_motion()
        self._fail(self.link.lost(), f"controller connection lost: {reason}")
        if writer is not None:
            with contextlib.suppress(Exception):
                writer.close()
        if was_ready and tell:
            log.error("controller at %s lost: %s", self.where, reason)
            self.listener.on_lost(reason)

