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

While the owner samples, the blocks a sample sends are acknowledged long before their
retransmission timeout (25 ms at least) and read at the next sample: when the owner says that
sample comes at most ``JUDGE_DEFER_MAX_S`` after the oldest block's timeout
(:meth:`Link.sample_due`), the sample judges it (resends it if it is still unacknowledged)
and the timer waits for it, instead of a wake-up of the process that only finds the
acknowledgement (one per block sent: a third of the wake-ups of a long move at a 0.2 s lead).
A lost block is resent that much later at most; a rest judges on the timeout again, and so
does everything in flight with an emergency stop sent first, until all is acknowledged, and a
resend (a second loss is resent on time: two in a row were late for their steps).

This module is the writing side: queueing, packing blocks, requests (riding ones too),
retransmission and the acknowledgement timeout. Reading the device (when: at the owner's
samples, or as data arrives while something must be read at once; and handing on what
arrives) is :class:`~.link_reader.LinkReader`, a base class of :class:`Link`.
"""

from __future__ import annotations

import asyncio
import os
import termios
import time
from collections import deque
from collections.abc import Callable

import serial

from server.backends.klipper.codec import PAYLOAD_MAX, BlockReader, Params
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.link_reader import BITS_PER_BYTE, LinkReader, Match
from server.backends.klipper.window import SendWindow

MessageHandler = Callable[[str, Params, float], None]
JUDGE_DEFER_MAX_S = 0.05
"""The most the judging of a block's retransmission timeout waits for the owner's next sample
(a lost block's resend comes that much later at most: 75 ms after it left instead of 25)."""
JUDGE_SLACK_S = 0.002  # the timer of a deferred judgement comes this much after the sample


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


class Link(LinkReader):
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
        self._sample_due_s: float | None = None  # the owner's next sample, as it said
        self._sent_first = False  # a message sent first is in flight: judged on time

    def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._fd = open_serial(self.path, self.baud)
        self._watch()

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
        self._sent_first = True  # its timeouts judged on time until the window is clear
        self._new_block(message, time.monotonic())
        self.send(*kept, keep=True)
        self._arm_timer()
        return dropped

    async def request(self, message: bytes, response: str, timeout_s: float,
                      match: Match = lambda _: True, ride_s: float = 0.0,
                      ride_after_s: float = 0.0) -> Params:
        """Send ``message`` and wait for the first ``response`` that ``match``es; its
        ``#sent_s`` is when ``message`` left. With ``ride_s``, ``message`` waits that long at
        most for other messages to leave and joins their first block, leaving no sooner than
        ``ride_after_s`` from now (``timeout_s`` counts from when it may have left at the
        latest)."""
        assert self._loop is not None
        future: asyncio.Future[Params] = self._loop.create_future()
        waiter = (response, match, future)
        self._waiters.append(waiter)
        rider = None
        sent_s = time.monotonic()
        if ride_s > 0.0 and self._rider is None and not self.closed:
            rider = self._rider = _Rider(message, sent_s + ride_after_s)
            rider.timer = self._loop.call_later(ride_after_s + ride_s, self._release_rider)
        else:
            self.send(message, keep=True)  # watched for its answer once it leaves (_pump)
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
        if (rider is not None and queue and not self.closed and now_s >= rider.earliest_s
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

    def sample_due(self, when_s: float) -> None:
        """The owner's next sample comes at ``when_s`` (at the latest, unless its ticks rest):
        a timeout due shortly before it is judged there (see the module docstring)."""
        self._sample_due_s = when_s
        self._arm_timer()

    def _arm_timer(self) -> None:
        """One timer, at the earliest deadline: kept while that deadline stands (blocks sent
        behind the oldest one in flight do not move it); while the owner samples, at its next
        sample if that comes within ``JUDGE_DEFER_MAX_S`` after the deadline."""
        deadline = self.window.deadline_s()
        if deadline is not None and self.ack_timeout_s is not None:
            deadline = min(deadline, self._progress_s + self.ack_timeout_s)
        if deadline is None:
            self._sent_first = False
        due_s = self._sample_due_s
        if (deadline is not None and due_s is not None and self.sampling
                and not self._sent_first and not self.window.recovering
                and deadline < due_s <= deadline + JUDGE_DEFER_MAX_S):
            deadline = due_s + JUDGE_SLACK_S
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
        self._judge()

    def _judge(self) -> None:
        """The acknowledgement timeout and the retransmission timeout, if passed, acted on;
        the timer armed for the next deadline."""
        if self.closed or self.failed or self._unacknowledged(time.monotonic()):
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
