"""Reading a Klipper MCU's link: when the device is read, and what is read is handled.

:class:`LinkReader` is the part of :class:`~.link.Link` (a base class of it) that reads the
device: it decides when the device is read (the owner's samples, the event loop's reader, a
settling read, the window's refill) and hands what arrives on: acknowledgements to the
:class:`~.window.SendWindow`, responses to the requests waiting for them and to
``on_message``, a broken stream to ``on_error``. Kept apart from the writing side in
:mod:`.link` (queueing, packing blocks, requests, retransmission) because when to read is a
subject of its own, which the CPU an idle or streaming board costs depends on; its state is
the link's, created by ``Link.__init__``.

While its owner samples (:meth:`LinkReader.sample`, the step generator's tick), the device is
read there, in one non-blocking drain, and not on every block that arrives: each wake-up of
the process costs CPU, and an MCU's faults are acted on at the next sample anyway. The event
loop watches the device only while something must be read at once: a request's answer awaited
once the request has left (a clock reading's arrival time is its measurement; a poll waiting
to ride along is not watched for), or no samples (:meth:`LinkReader.rest`: an idle board's
shutdown or restart is read at once). Every timer that judges the link (retransmission, the
acknowledgement timeout) drains it first. Messages waiting for room in the window while the
owner samples are not a reason to read every acknowledgement as it comes (a wake-up each, and
another for the rest of its block): the device is drained once, when the wire has carried what
is in flight and the acknowledgement of its last block (``_wire_free_s``: the blocks written,
back to back at the baud rate), and what fits then leaves; only a board slower than its wire
(that drain found nothing acknowledged) has its acknowledgements read as they arrive, until
the window moves again. Acknowledgements read at a sample or such a drain are late: they
measure no round trip.
Read as data arrives, a block comes a few bytes at a time on a serial line (40 µs a byte at
250,000 baud), and an answer is followed by the empty block that acknowledges the command's:
a read that ends inside a block, or just after an answer, waits the wire time of the rest
(:meth:`LinkReader._settle_bytes`) before reading again, instead of waking for every byte or
two.
"""

from __future__ import annotations

import asyncio
import os
import select
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from server.backends.klipper.codec import (
    MESSAGE_MAX,
    MESSAGE_MIN,
    BlockReader,
    Params,
    ProtocolError,
)
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.window import SendWindow, SequenceError

if TYPE_CHECKING:
    from server.backends.klipper.link import _Rider

READ_BYTES = 1024  # per turn of the event loop: a board that floods delays a status report
# by one such turn (~2 ms of decoding), never more
Match = Callable[[Params], bool]
BITS_PER_BYTE = 10  # a start bit, 8 data bits, a stop bit
SETTLE_SLACK = 1.25  # the wire time waited for the rest of a block, and then some
SETTLE_MAX_S = 0.005  # at most (a slow link's block is read in parts)
REFILL_MARGIN_S = 0.001  # a window's drain comes this much after its acknowledgements' wire time


class LinkReader:
    """When the device is read, and what is read; see the module docstring."""

    # The link's state this part reads and writes (set by Link.__init__).
    path: str
    baud: int
    dictionary: Dictionary
    window: SendWindow
    bytes_received: int
    _on_message: Callable[[str, Params, float], None]
    _on_error: Callable[[str], None]
    _reader: BlockReader
    _queue: deque[bytes]
    _waiters: list[tuple[str, Match, asyncio.Future[Params]]]
    _rider: _Rider | None
    _fd: int | None
    _loop: asyncio.AbstractEventLoop | None
    closed: bool
    failed: bool
    _blocks_in: int
    sampling: bool
    watched: bool
    drains: int
    _backlog: bool
    _settle: asyncio.TimerHandle | None
    _answered: bool
    _wire_free_s: float
    _refill: asyncio.TimerHandle | None
    _slow: bool
    refills: int
    _sample_due_s: float | None

    if TYPE_CHECKING:  # the writing side's (.link)
        def _pump(self) -> None: ...
        def _write(self, data: bytes, flush: bool = True) -> None: ...
        def _moved(self, now_s: float) -> None: ...
        def _unacknowledged(self, now_s: float) -> bool: ...
        def _fail(self, reason: str) -> None: ...
        def _fail_waiters(self, reason: str) -> None: ...
        def _judge(self) -> None: ...

    def sample(self) -> None:
        """The owner's tick: read what the device holds, judge the timeouts passed (the timer
        may have waited for this sample: see :mod:`.link`), then watch the device only while
        something must be read at once (see the module docstring)."""
        self.sampling = True
        self._sample_due_s = None  # until the owner says when the next one comes
        self._drain()
        self._judge()
        self._watch()

    def rest(self) -> None:
        """The owner stops sampling: the event loop reads the device as data arrives (and the
        timeouts are judged when they pass)."""
        self.sampling = False
        self._sample_due_s = None
        self._judge()
        self._watch()

    def _watch(self) -> None:
        """Register or remove the reader for what must be read now (not while a read waits
        for the rest of a block: the settling read decides then)."""
        if (self._fd is None or self._loop is None or self.closed or self.failed
                or self._settle is not None):
            return
        want = self._wants_reader()
        if want and not self.watched:
            self._loop.add_reader(self._fd, self._on_readable)
        elif not want and self.watched:
            self._loop.remove_reader(self._fd)
        self.watched = want
        if want or not self._queue:
            if self._refill is not None:
                self._refill.cancel()
                self._refill = None
        elif self._refill is None:  # room for what waits: when the window has been acked
            self._arm_refill()

    def _arm_refill(self) -> None:
        """The drain for what waits, once the wire has carried what was written and the last
        block's acknowledgement has come back."""
        assert self._loop is not None
        wire_s = max(0.0, self._wire_free_s - time.monotonic())
        ack_s = MESSAGE_MIN * BITS_PER_BYTE * SETTLE_SLACK / self.baud
        self._refill = self._loop.call_later(wire_s + ack_s + REFILL_MARGIN_S, self._on_refill)

    def _wants_reader(self) -> bool:
        """Whether something must be read as it arrives (see the module docstring)."""
        answer_due = bool(self._waiters) and self._rider is None  # a rider has not left yet
        waiting = bool(self._queue) and self._slow  # acks as they come from a slow board
        return not self.sampling or self._backlog or answer_due or waiting

    def _on_refill(self) -> None:
        """The window's acknowledgements should have arrived: read them, send what fits."""
        self._refill = None
        if self.closed or self.failed:
            return
        acked = self.window.acked
        self.refills += 1
        self._drain()  # its blocks handled, what fits sent, the next refill armed (_pump)
        if (self._queue and self.window.acked == acked and self.window.inflight
                and not self.closed and not self.failed):
            self._slow = True  # nothing acknowledged in the wire's time: read as they come
        self._watch()

    def _poll_events(self) -> int:
        """The device's poll events now (no wait)."""
        assert self._fd is not None
        poll = select.poll()
        poll.register(self._fd, select.POLLIN)
        ready = poll.poll(0)
        return ready[0][1] if ready else 0

    def read_waiting(self) -> None:
        """Read what the device holds now (a judge of the link's silence reads it first)."""
        self._drain()
        self._watch()

    def _drain(self) -> None:
        """Read what the device holds now, non-blocking: one read of ``READ_BYTES``; if that
        filled it, the rest is read a turn of the event loop at a time, as it would be while
        watched (a flooding board delays others by one read, never more)."""
        if self._fd is not None and not self.closed and not self.failed:
            self._backlog = self._read(timed=False) >= READ_BYTES

    def _on_readable(self) -> None:
        self._settle = None
        if self.closed or self.failed:
            return
        got = self._read(timed=not self._backlog)
        if got < READ_BYTES:
            self._backlog = False
        missing = self._settle_bytes() if got else 0  # nothing came: the reader waits
        if (not missing or self.closed or self.failed or self._loop is None
                or not self._wants_reader()):
            self._watch()
            return
        if self.watched:  # the rest is read after its wire time, not byte by byte
            assert self._fd is not None
            self._loop.remove_reader(self._fd)
            self.watched = False
        self._settle = self._loop.call_later(
            min(SETTLE_MAX_S, missing * BITS_PER_BYTE * SETTLE_SLACK / self.baud),
            self._on_readable)

    def _settle_bytes(self) -> int:
        """The bytes still on their way: the rest of a block begun, and the acknowledgement
        that follows an answer (an empty block); 0 after an acknowledgement or garbage."""
        buffer = self._reader.buffer
        if buffer:
            length = buffer[0]
            if not MESSAGE_MIN <= length <= MESSAGE_MAX:
                return 0
            return length - len(buffer) + (MESSAGE_MIN if length > MESSAGE_MIN else 0)
        return MESSAGE_MIN if self._answered else 0

    def _read(self, timed: bool) -> int:
        """One read of the device, its blocks handled; the bytes read. ``timed``: read as
        they arrived (acknowledgements then measure the round trip)."""
        assert self._fd is not None
        try:
            data = os.read(self._fd, READ_BYTES)
            # a raw tty with nothing to read reads empty too (VMIN = VTIME = 0), and a sample
            # may have read what woke the reader: closed only if it hangs up, or is ready
            # and still reads empty
            if not data:
                events = self._poll_events()
                if not events:
                    return 0
                if not events & (select.POLLHUP | select.POLLERR | select.POLLNVAL):
                    data = os.read(self._fd, READ_BYTES)
        except BlockingIOError:
            return 0
        except OSError as exc:
            self._fail(f"cannot read from {self.path}: {exc.strerror}")
            return 0
        if not data:
            self._fail(f"{self.path} was closed")
            return 0
        self.bytes_received += len(data)
        if not timed:
            self.drains += 1
        now_s = time.monotonic()
        acked = self.window.acked
        try:
            for block in self._reader.feed(data):
                self._blocks_in += 1
                for again in self.window.on_block(block.seq, not block.payload, now_s, timed):
                    self._write(again)
                self._answered = bool(block.payload)
                if block.payload:
                    self._deliver(self.dictionary.decode(block.payload), now_s)
        except (SequenceError, ProtocolError) as exc:
            self._broken(str(exc))
            return 0
        if self.window.acked != acked:
            self._moved(now_s)
        elif self._unacknowledged(now_s):  # a board that talks but never acknowledges
            return 0
        self._pump()
        return len(data)

    def _deliver(self, messages: list[tuple[str, Params]], now_s: float) -> None:
        for name, params in messages:
            params["#received_s"] = now_s
            for waiter in list(self._waiters):
                wanted, match, future = waiter
                if wanted == name and not future.done() and match(params):
                    future.set_result(params)
                    self._waiters.remove(waiter)
                    break
            self._on_message(name, params, now_s)

    def _broken(self, reason: str) -> None:
        """The MCU's answers cannot be trusted any more: stop reading them and report once;
        writing still works until :meth:`close` (the emergency stop goes out first)."""
        if self.closed or self.failed:
            return
        self.failed = True
        assert self._loop is not None and self._fd is not None
        self._loop.remove_reader(self._fd)
        self.watched = False
        self._on_error(reason)
        self._fail_waiters(reason)  # no answer can come: a request waits no longer
