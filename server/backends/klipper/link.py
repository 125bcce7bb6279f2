"""The serial link to a Klipper MCU: a device or pty path, its own thread, asyncio.

The link's thread (:class:`~._stepcore.SerialQueue`, compiled: ``_serialq.c``) owns the
device, as klippy's serialqueue does for klippy: it packs the messages sent into message
blocks (as many as fit in 59 bytes) while the MCU's receive window has room, reads every block
as it arrives and stamps it with its arrival time (``time.monotonic``), acknowledges what was
sent, resends on a nak or a retransmission timeout, refills the window as acknowledgements
free it, and judges the acknowledgement timeout. None of that wakes the event loop: a wake-up
of the interpreter costs far more than one of that thread.

The responses it keeps are decoded here, with the current :class:`~.dictionary.Dictionary`,
and handed to ``on_message`` with their arrival time: at the owner's samples (the step
generator's ticks, :meth:`Link.sample`), or at once when the thread signals them, which it does
while something must be read at once: an answer awaited (but a riding poll's: a clock
reading's arrival time is its measurement, stamped by the thread, so a poll riding the steps is
answered at the next sample), or no samples (:meth:`Link.rest`: an idle board's shutdown or
restart is read at once). A fault of the link is always signalled at once.

:meth:`Link.request` sends one command and waits for a matching response; a request that may
ride (``ride_s``: a poll while steps flow) waits that long at most for other messages to share
their block instead of taking one of its own (5 bytes of framing for 1 or 2), and its response
says when it left (``#sent_s``), as every request's does. A closed device is reported once to
``on_error`` and the link closed; an unreadable block stream, a restarted MCU (a sequence
number never sent) or, once ``ack_timeout_s`` is set, a block left unacknowledged that long (a
board that is silent, sends garbage, or floods messages without acknowledging ours) is
reported once and nothing more is read, but an emergency stop can still be written before
:meth:`Link.close`. Either way the link is dead and must be replaced.
"""

from __future__ import annotations

import asyncio
import logging
import os
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial

from server.backends.klipper.codec import Params, ProtocolError
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.stepcore import SerialQueue

log = logging.getLogger("motiond.klipper")
MessageHandler = Callable[[str, Params, float], None]
Match = Callable[[Params], bool]
READ_BYTES = 1024  # of responses decoded per turn of the event loop: a board that floods
# delays a status report by one such turn (~2 ms of decoding), never more


@dataclass(eq=False, slots=True)
class _Waiter:
    response: str
    match: Match
    future: asyncio.Future[Params]
    lazy: bool  # its answer may wait for the owner's next sample (a poll riding the steps)


class _Rider:
    """A request waiting to share a block with other messages: when it left, once it has."""

    def __init__(self, message: bytes, earliest_s: float) -> None:
        self.message, self.earliest_s = message, earliest_s  # it joins no block before this
        self.sent_s: float | None = None
        self.timer: asyncio.TimerHandle | None = None


def open_serial(path: str, baud: int) -> int:
    """Open a device or pty raw and non-blocking at ``baud`` (any rate, 250000 included:
    pyserial sets rates termios has no constant for); USB CDC ignores the rate."""
    try:
        port = serial.Serial(path, baud, timeout=0)
    except (serial.SerialException, termios.error, ValueError):  # not a terminal (a pipe)
        return os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        fd = os.dup(port.fileno())  # the settings belong to the device; the copy keeps them
    finally:
        port.close()
    os.set_blocking(fd, False)
    return fd


class Link:
    """One open connection to an MCU; see the module docstring."""

    def __init__(self, path: str, baud: int, on_message: MessageHandler,
                 on_error: Callable[[str], None], window_bytes: int = 192) -> None:
        self.path, self.baud = path, baud
        self.dictionary = Dictionary.bootstrap()
        self._window_bytes = window_bytes
        self._ack_timeout_s: float | None = None  # None: no limit (connecting, a slow boot)
        self._on_message, self._on_error = on_message, on_error
        self._queue: SerialQueue | None = None
        self._waiters: list[_Waiter] = []
        self._rider: _Rider | None = None  # a request waiting for company (one at a time)
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.closed = False
        self.failed = False  # a broken stream from the MCU: nothing more is read
        self.sampling = False  # the owner samples: responses are taken at its samples
        self.signalled = False  # the thread signals each response as it arrives
        self.wakes = 0  # the event loop woken by the thread's signal (for tests)

    def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._fd = open_serial(self.path, self.baud)
        self._queue = SerialQueue(self._fd, self._window_bytes)
        self._queue.ack_timeout_s = self._ack_timeout_s
        self._loop.add_reader(self._queue.notify_fd, self._on_signal)
        self._watch()

    # -- the thread's state -----------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """The thread's counts (``SerialQueue.stats``): bytes, blocks, retransmits, rtt."""
        return self._queue.stats() if self._queue is not None else {}

    @property
    def bytes_sent(self) -> int:
        return self._queue.bytes_sent if self._queue is not None else 0

    @property
    def bytes_received(self) -> int:
        return self._queue.bytes_received if self._queue is not None else 0

    @property
    def queued_bytes(self) -> int:
        """Message bytes waiting for room in the window."""
        return self._queue.queued_bytes if self._queue is not None else 0

    @property
    def in_flight(self) -> int:
        """Blocks sent and not yet acknowledged."""
        return self._queue.in_flight if self._queue is not None else 0

    @property
    def retransmits(self) -> int:
        return int(self.stats().get("retransmits", 0))

    def inflight_payloads(self) -> list[bytes]:
        """The payloads of the blocks not yet acknowledged, oldest first."""
        return self._queue.inflight() if self._queue is not None else []

    def queued(self) -> list[bytes]:
        """The messages waiting for room in the window, in order."""
        return self._queue.queued() if self._queue is not None else []

    @property
    def window_bytes(self) -> int:
        """The MCU's receive window (its ``RECEIVE_WINDOW``)."""
        return self._window_bytes

    @window_bytes.setter
    def window_bytes(self, size: int) -> None:
        self._window_bytes = size
        if self._queue is not None:
            self._queue.window_bytes = size

    @property
    def ack_timeout_s(self) -> float | None:
        """A block left unacknowledged this long is a fault (None: no limit)."""
        return self._ack_timeout_s

    @ack_timeout_s.setter
    def ack_timeout_s(self, timeout_s: float | None) -> None:
        self._ack_timeout_s = timeout_s
        if self._queue is not None:
            self._queue.ack_timeout_s = timeout_s

    # -- sending ----------------------------------------------------------------------------
    def send(self, *messages: bytes, keep: bool = False) -> None:
        """Queue encoded commands; they go out as soon as the window allows, as many to a
        block as fit (messages sent together share blocks: send a burst in one call); a
        riding request whose time has come joins the first."""
        queue, rider = self._queue, self._rider
        if queue is None or self.closed or not messages:
            return
        if rider is not None and time.monotonic() >= rider.earliest_s:
            self._drop_rider()  # it leaves now, in the first block
            rider.sent_s = time.monotonic()
            queue.send((rider.message, *messages), keep, 1)
        else:
            queue.send(messages, keep)

    def send_first(self, message: bytes) -> list[bytes]:
        """Send ``message`` now, before everything not yet sent, which is dropped and returned
        but for requests (an emergency stop must not wait behind the steps it cancels, nor for
        room in the window: it goes out in a block of its own at once)."""
        if self._queue is None:
            return []
        try:
            return self._queue.send_first(message)
        except BufferError as exc:  # a board that acknowledged none of 15 blocks: its
            log.warning("%s: not sent: %s", self.path, exc)  # silence is judged soon
            return []

    async def request(self, message: bytes, response: str, timeout_s: float,
                      match: Match = lambda _: True, ride_s: float = 0.0,
                      ride_after_s: float = 0.0) -> Params:
        """Send ``message`` and wait for the first ``response`` that ``match``es; its
        ``#sent_s`` is when ``message`` left. With ``ride_s``, ``message`` waits that long at
        most for other messages to leave and joins their first block, leaving no sooner than
        ``ride_after_s`` from now (``timeout_s`` counts from when it may have left at the
        latest); a riding request's answer is taken at the owner's next sample if it
        samples."""
        assert self._loop is not None
        future: asyncio.Future[Params] = self._loop.create_future()
        rider = None
        sent_s = time.monotonic()
        if ride_s > 0.0 and self._rider is None and not self.closed:
            rider = self._rider = _Rider(message, sent_s + ride_after_s)
            rider.timer = self._loop.call_later(ride_after_s + ride_s, self._release_rider)
        waiter = _Waiter(response, match, future, rider is not None)
        self._waiters.append(waiter)
        if rider is None:
            self.send(message, keep=True)
        self._watch()
        try:
            # its patience starts when it leaves: a rider waits for company until its time
            ride_for_s = ride_after_s + ride_s if rider else 0.0
            params = await asyncio.wait_for(future, timeout_s + ride_for_s)
        finally:
            if waiter in self._waiters:
                self._waiters.remove(waiter)
            if rider is not None and rider is self._rider:  # never left (a timeout, a close)
                self._drop_rider()
            self._watch()
        params["#sent_s"] = sent_s if rider is None or rider.sent_s is None else rider.sent_s
        return params

    def hurry(self) -> None:
        """A request waiting to ride leaves now, and every answer awaited is read as it
        arrives (the end of motion is confirmed by a reading of the board's clock)."""
        self._release_rider()
        for waiter in self._waiters:
            waiter.lazy = False
        self._watch()

    def _release_rider(self) -> None:
        """The rider leaves on its own (no company came in time, or it is hurried)."""
        rider = self._rider
        if rider is not None:
            self._drop_rider()  # (its timer cancelled: harmless when it is this call)
            rider.sent_s = time.monotonic()
            self.send(rider.message, keep=True)

    def _drop_rider(self) -> None:
        if self._rider is not None and self._rider.timer is not None:
            self._rider.timer.cancel()
        self._rider = None

    # -- receiving --------------------------------------------------------------------------
    def sample(self) -> None:
        """The owner's tick: take what arrived since the last one; from now on, responses
        wait for its samples unless an answer is awaited."""
        self.sampling = True
        self._take()
        self._watch()

    def rest(self) -> None:
        """The owner stops sampling: responses are taken as they arrive again."""
        self.sampling = False
        self._watch()

    def read_waiting(self) -> None:
        """Take what arrived now (a judge of the link's silence reads it first)."""
        self._take()
        self._watch()

    def _on_signal(self) -> None:
        self.wakes += 1
        self._take()
        self._watch()

    def _watch(self) -> None:
        """Have the thread signal each response while one must be read at once (see the
        module docstring)."""
        if self._queue is None or self.closed or self.failed:
            return
        want = not self.sampling or any(not waiter.lazy for waiter in self._waiters)
        if want != self.signalled:
            self._queue.set_notify(want)
            self.signalled = want

    def _take(self) -> None:
        """The responses the thread kept, decoded and handed on, up to ``READ_BYTES`` a turn
        of the event loop; then the fault that ended the link, if one did."""
        queue = self._queue
        if queue is None or self.closed or self.failed:
            return
        blocks, fault, more = queue.pull(READ_BYTES)
        for payload, received_s in blocks:
            if self.closed or self.failed:
                return
            try:
                messages = self.dictionary.decode(payload)
            except ProtocolError as exc:
                self._broken(str(exc))
                return
            self._deliver(messages, received_s)
        if fault is not None:
            kind, text = fault
            if kind == "broken":
                self._broken(text)
            elif kind == "hangup":
                self._fail(f"{self.path} was closed")
            else:
                verb = "read from" if kind == "read" else "write to"
                self._fail(f"cannot {verb} {self.path}: {text}")
        elif more and self._loop is not None and not self.closed:
            self._loop.call_soon(self.read_waiting)  # a flood: the rest a turn at a time

    def _deliver(self, messages: list[tuple[str, Params]], received_s: float) -> None:
        for name, params in messages:
            params["#received_s"] = received_s
            for waiter in self._waiters:
                if waiter.response == name and not waiter.future.done() and waiter.match(params):
                    waiter.future.set_result(params)
                    self._waiters.remove(waiter)
                    break
            self._on_message(name, params, received_s)

    def _broken(self, reason: str) -> None:
        """The MCU's answers cannot be trusted any more: stop reading them and report once;
        writing still works until :meth:`close` (the emergency stop goes out first)."""
        if self.closed or self.failed:
            return
        self.failed = True
        if self._queue is not None:
            self._queue.halt(reason)
        self._on_error(reason)
        self._fail_waiters(reason)  # no answer can come: a request waits no longer

    def _fail(self, reason: str) -> None:
        if not self.closed:
            self.close()
            self._on_error(reason)

    def _fail_waiters(self, reason: str) -> None:
        for waiter in self._waiters:
            if not waiter.future.done():
                waiter.future.set_exception(ConnectionError(reason))
        self._waiters.clear()

    def close(self) -> None:
        """Stop reading and writing and release the device; safe twice."""
        if self.closed:
            return
        self.closed = True
        self._drop_rider()
        self._fail_waiters(f"link to {self.path} closed")
        if self._queue is not None:
            self._queue.close()
            if self._loop is not None:
                self._loop.remove_reader(self._queue.notify_fd)
        if self._fd is not None:
            os.close(self._fd)
        self._fd = None
