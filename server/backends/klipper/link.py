"""The serial link to a Klipper MCU: a device or pty path, asyncio, non-blocking.

Outgoing messages are packed in order into message blocks (as many as fit in 59 bytes) while
the :class:`~.window.SendWindow` has room; incoming blocks acknowledge them and carry the MCU's
responses, which are decoded with the current :class:`~.dictionary.Dictionary` and handed to
``on_message`` with their arrival time (``time.monotonic``, the clock the event loop and the
kernel use). :meth:`Link.request` sends one command and waits for a matching response; a
request that may ride (``ride_s``: a poll while steps flow) waits that long at most for other
messages to share their block instead of taking one of its own (5 bytes of framing for 1 or 2),
and its response says when it left (``#sent_s``), as every request's does.
A closed device is reported once to ``on_error`` and the link closed; an unreadable block
stream, a restarted MCU (a sequence number never sent) or, once ``ack_timeout_s`` is set, a
block left unacknowledged that long (a board that is silent, sends garbage, or floods messages
without acknowledging ours) is reported once and nothing more is read, but an emergency stop
can still be written before :meth:`Link.close`. Either way the link is dead and must be replaced.

Reading: while its owner samples (:meth:`Link.sample`, the step generator's tick), the device
is read there, in one non-blocking drain, and not on every block that arrives: each wake-up of
the process costs CPU, and an MCU's faults are acted on at the next sample anyway. The event
loop watches the device only while something must be read at once: a request's answer awaited
once the request has left (a clock reading's arrival time is its measurement; a poll waiting
to ride along is not watched for), or no samples (:meth:`Link.rest`: an idle board's
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
(:meth:`Link._settle_bytes`) before reading again, instead of waking for every byte or two.
"""

from __future__ import annotations

import asyncio
import os
import select
import termios
import time
from collections import deque
from collections.abc import Callable

import serial

from server.backends.klipper.codec import (
    MESSAGE_MAX,
    MESSAGE_MIN,
    PAYLOAD_MAX,
    BlockReader,
    Params,
    ProtocolError,
)
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.window import SendWindow, SequenceError

MessageHandler = Callable[[str, Params, float], None]
READ_BYTES = 1024  # per turn of the event loop: a board that floods delays a status report
# by one such turn (~2 ms of decoding), never more
Match = Callable[[Params], bool]
BITS_PER_BYTE = 10  # a start bit, 8 data bits, a stop bit
SETTLE_SLACK = 1.25  # the wire time waited for the rest of a block, and then some
SETTLE_MAX_S = 0.005  # at most (a slow link's block is read in parts)
REFILL_MARGIN_S = 0.001  # a window's drain comes this much after its acknowledgements' wire time


class _Rider:
    """A request waiting to share a block with other messages: when it left, once it has."""

    def __init__(self, message: bytes) -> None:
        self.message = message
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
        self.window = SendWindow(window_bytes)
        self.bytes_sent = 0
        self.bytes_received = 0
        self._on_message, self._on_error = on_message, on_error
        self._reader = BlockReader()
        self._queue: deque[bytes] = deque()
        self._keep: deque[bool] = deque()  # per queued message: a request's (never dropped)
        self._out = bytearray()
        self._waiters: list[tuple[str, Match, asyncio.Future[Params]]] = []
        self._rider: _Rider | None = None  # a request waiting for company (one at a time)
        self._timer: asyncio.TimerHandle | None = None
        self._timer_deadline_s = 0.0  # when the armed timer fires
        self._writing = False  # the event loop waits for room to write the rest of _out
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.closed = False
        self.failed = False  # a broken stream from the MCU: nothing more is read
        self.ack_timeout_s: float | None = None  # None: no limit (connecting, a slow boot)
        self._progress_s = 0.0  # when the window last moved (a block acknowledged or sent)
        self._blocks_in = 0  # valid blocks received since then
        self._bad_at_progress = 0  # the reader's count of damaged blocks then
        self.sampling = False  # the owner samples: the device is read at its samples
        self.watched = False  # the event loop reads the device as data arrives
        self.drains = 0  # reads of what waited: samples, timers, refills (for tests)
        self._backlog = False  # a sample's read filled READ_BYTES: more waits to be read
        self._settle: asyncio.TimerHandle | None = None  # the read after the rest's wire time
        self._answered = False  # the last block read was an answer (its acknowledgement follows)
        self._wire_free_s = 0.0  # when the wire will have carried every byte written
        self._refill: asyncio.TimerHandle | None = None  # the drain when the window is acked
        self._slow = False  # a refill found nothing acknowledged: read acks as they arrive
        self.refills = 0  # of those, the window's refills (for tests)

    def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._fd = open_serial(self.path, self.baud)
        self._watch()

    def sample(self) -> None:
        """The owner's tick: read what the device holds, then watch it only while something
        must be read at once (see the module docstring)."""
        self.sampling = True
        self._drain()
        self._watch()

    def rest(self) -> None:
        """The owner stops sampling: the event loop reads the device as data arrives."""
        self.sampling = False
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

    @property
    def queued_bytes(self) -> int:
        """Message bytes waiting for room in the window."""
        return sum(len(m) for m in self._queue)

    def send(self, *messages: bytes, keep: bool = False) -> None:
        """Queue encoded commands; they go out as soon as the window allows, as many to a
        block as fit (messages sent together share blocks: send a burst in one call)."""
        if not self.closed:
            self._queue.extend(messages)
            self._keep.extend([keep] * len(messages))
            self._pump()

    def send_first(self, message: bytes) -> list[bytes]:
        """Send ``message`` now, before everything not yet sent, which is dropped and returned
        but for requests (an emergency stop must not wait behind the steps it cancels, nor for
        room in the window: it goes out in a block of its own at once)."""
        kept = [m for m, k in zip(self._queue, self._keep, strict=True) if k]
        dropped = [m for m, k in zip(self._queue, self._keep, strict=True) if not k]
        self._queue.clear()
        self._keep.clear()
        if self.closed:
            return dropped
        self._new_block(message, time.monotonic())
        self.send(*kept, keep=True)
        self._arm_timer()
        return dropped

    async def request(self, message: bytes, response: str, timeout_s: float,
                      match: Match = lambda _: True, ride_s: float = 0.0) -> Params:
        """Send ``message`` and wait for the first ``response`` that ``match``es; its
        ``#sent_s`` is when ``message`` left. With ``ride_s``, ``message`` waits that long at
        most for other messages to leave and joins their first block (``timeout_s`` counts
        from when it may have left at the latest)."""
        assert self._loop is not None
        future: asyncio.Future[Params] = self._loop.create_future()
        waiter = (response, match, future)
        self._waiters.append(waiter)
        rider = None
        sent_s = time.monotonic()
        if ride_s > 0.0 and self._rider is None and not self.closed:
            rider = self._rider = _Rider(message)
            rider.timer = self._loop.call_later(ride_s, self._release_rider)
        else:
            self.send(message, keep=True)  # watched for its answer once it leaves (_pump)
        try:
            # its patience starts when it leaves: a rider waits up to ride_s for company
            params = await asyncio.wait_for(future, timeout_s + (ride_s if rider else 0.0))
        finally:
            if waiter in self._waiters:
                self._waiters.remove(waiter)
            if rider is not None and rider is self._rider:  # never left (a timeout, a close)
                self._drop_rider()
            self._watch()
        params["#sent_s"] = sent_s if rider is None or rider.sent_s is None else rider.sent_s
        return params

    def _release_rider(self) -> None:
        """No company came in time: the rider leaves on its own."""
        rider = self._rider
        if rider is not None:
            self._rider, rider.timer, rider.sent_s = None, None, time.monotonic()
            self.send(rider.message, keep=True)

    def _drop_rider(self) -> None:
        if self._rider is not None and self._rider.timer is not None:
            self._rider.timer.cancel()
        self._rider = None

    def _pump(self) -> None:
        now_s = time.monotonic()
        rider = self._rider
        queue, window = self._queue, self.window
        if (rider is not None and queue and not self.closed
                and window.can_send(len(rider.message) + len(queue[0]) + 5)):
            self._drop_rider()  # it leaves now, in the first block
            rider.sent_s = now_s
            queue.appendleft(rider.message)
            self._keep.appendleft(True)
        made = False
        while queue and not self.closed:
            payload = bytearray()
            while queue and len(payload) + len(queue[0]) <= PAYLOAD_MAX:
                if not window.can_send(len(payload) + len(queue[0]) + 5):
                    break
                payload += queue.popleft()
                self._keep.popleft()
            if not payload:
                break
            self._new_block(bytes(payload), now_s, flush=False)
            made = True
        if made:
            self._flush_out()  # the blocks of a burst in one write
        self._arm_timer()
        self._watch()  # messages left waiting for room: acknowledgements read as they come

    def _arm_timer(self) -> None:
        """One timer, at the earliest deadline: kept while that deadline stands (blocks sent
        behind the oldest one in flight do not move it)."""
        deadline = self.window.deadline_s()
        if deadline is not None and self.ack_timeout_s is not None:
            deadline = min(deadline, self._progress_s + self.ack_timeout_s)
        if self.closed or self._loop is None:
            deadline = None
        if self._timer is not None:
            if deadline == self._timer_deadline_s:
                return
            self._timer.cancel()
            self._timer = None
        if deadline is not None and self._loop is not None:
            self._timer_deadline_s = deadline
            delay = max(0.0, deadline - time.monotonic())
            self._timer = self._loop.call_later(delay, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        if not self.watched:  # what arrived since the last sample first
            self._drain()
            if self.closed or self.failed or self._timer is not None:
                return  # judged (or re-armed by what was read) already
        if self._unacknowledged(time.monotonic()):
            return
        for block in self.window.on_timer(time.monotonic()):
            self._write(block)
        self._arm_timer()

    def _unacknowledged(self, now_s: float) -> bool:
        """Whether a block has waited ``ack_timeout_s`` for its acknowledgement (reported)."""
        if (self.ack_timeout_s is None or self.failed or not self.window.inflight
                or now_s - self._progress_s <= self.ack_timeout_s):
            return False
        bad = self._reader.bad_blocks - self._bad_at_progress
        seen = f"{self._blocks_in} blocks and {bad} damaged" if self._blocks_in or bad else \
            "nothing"
        self._broken(f"the MCU acknowledged none of {len(self.window.inflight)} blocks for "
                     f"{now_s - self._progress_s:.2f} s (it sent {seen} meanwhile)")
        return True

    def _new_block(self, payload: bytes, now_s: float, flush: bool = True) -> None:
        if not self.window.inflight:  # the wait for an acknowledgement starts now
            self._moved(now_s)
        self._write(self.window.make_block(payload, now_s), flush)

    def _moved(self, now_s: float) -> None:
        self._progress_s = now_s
        self._slow = False
        self._blocks_in, self._bad_at_progress = 0, self._reader.bad_blocks

    def _write(self, data: bytes, flush: bool = True) -> None:
        self._out += data
        self.bytes_sent += len(data)
        if flush:
            self._flush_out()

    def _flush_out(self) -> None:
        if self._fd is None or self.closed:
            return
        try:
            written = os.write(self._fd, self._out) if self._out else 0
        except BlockingIOError:
            written = 0
        except OSError as exc:
            self._fail(f"cannot write to {self.path}: {exc.strerror}")
            return
        del self._out[:written]
        if written:  # back to back on the wire after what is still on it
            now_s = time.monotonic()
            self._wire_free_s = (max(now_s, self._wire_free_s)
                                 + written * BITS_PER_BYTE / self.baud)
            if self._refill is not None:  # later: what was just written is acked then too
                self._refill.cancel()
                self._arm_refill()
        assert self._loop is not None
        if bool(self._out) != self._writing:  # the loop watches for room only while needed
            self._writing = bool(self._out)
            if self._writing:
                self._loop.add_writer(self._fd, self._flush_out)
            else:
                self._loop.remove_writer(self._fd)

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

    def _fail(self, reason: str) -> None:
        if not self.closed:
            self.close()
            self._on_error(reason)

    def _fail_waiters(self, reason: str) -> None:
        for _, _, future in self._waiters:
            if not future.done():
                future.set_exception(ConnectionError(reason))
        self._waiters.clear()

    def close(self) -> None:
        """Stop reading and writing and release the device; safe twice."""
        if self.closed:
            return
        self.closed = True
        if self._timer is not None:
            self._timer.cancel()
        if self._settle is not None:
            self._settle.cancel()
        if self._refill is not None:
            self._refill.cancel()
        self._drop_rider()
        self._fail_waiters(f"link to {self.path} closed")
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
            self._loop.remove_writer(self._fd)
            os.close(self._fd)
        self._fd = None
