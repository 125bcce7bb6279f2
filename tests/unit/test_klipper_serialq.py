"""The link's thread (``SerialQueue``, ``_serialq.c``) over real I/O: it owns one end of a
``socket.socketpair()`` and the test plays the MCU on the other, scripting the bytes a board
would send, the faults included that the firmware rigs cannot produce on demand (naks, a
restart, a board that served a host before, floods, garbage, silence, a hangup).

The window's rules are those of the pure-Python SendWindow it replaced (acks, naks, timeouts,
restarts, adoption of a running MCU's count); timing is asserted loosely (orders, counts,
lower bounds the thread cannot beat, upper bounds of a second), so a loaded machine passes.
"""

from __future__ import annotations

import re
import select
import socket
import time
from collections.abc import Callable, Iterator

import pytest

from server.backends.klipper._stepcore import SerialQueue, frame

RTO_S = 0.1  # the retransmission timeout before any measurement
SLOW_S = 0.05  # a board answering its first block this late makes the timeout ~0.15 s: time
# for a test's next steps on a loaded machine before anything is resent

Block = tuple[int, bytes]  # (seq4, payload)
Fault = tuple[str, str]


def block(seq4: int, payload: bytes = b"") -> bytes:
    """A block from the MCU: an ack (empty) or a response, acknowledging up to ``seq4``."""
    return frame(0x10 | (seq4 & 0x0F), payload)


class Board:
    """The MCU's end: reads the host's blocks, writes its own."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buf = bytearray()
        self.expected = 0  # the next block the firmware would accept (a 64-bit count)

    def write(self, *blocks: bytes) -> None:
        self.sock.sendall(b"".join(blocks))

    def _split(self) -> Block | None:
        if not self.buf or len(self.buf) < self.buf[0]:
            return None
        raw = bytes(self.buf[:self.buf[0]])
        del self.buf[:len(raw)]
        assert frame(raw[1], raw[2:-3]) == raw and raw[1] & 0xF0 == 0x10, raw.hex()
        return raw[1] & 0x0F, raw[2:-3]

    def next_block(self, until_s: float) -> Block | None:
        """The next block the host sent, waiting until ``until_s`` at most."""
        while (got := self._split()) is None:
            left = until_s - time.monotonic()
            if left <= 0 or not select.select([self.sock], [], [], left)[0]:
                return None
            data = self.sock.recv(65536)
            if not data:
                return None
            self.buf += data
        return got

    def blocks(self, count: int, timeout_s: float = 2.0) -> list[Block]:
        """The next ``count`` blocks as sent (resends included)."""
        until_s = time.monotonic() + timeout_s
        got: list[Block] = []
        while len(got) < count and (one := self.next_block(until_s)) is not None:
            got.append(one)
        assert len(got) == count, f"{len(got)} of {count} blocks came: {got}"
        return got

    def quiet(self, timeout_s: float) -> bool:
        """Nothing arrives for ``timeout_s``."""
        return self.next_block(time.monotonic() + timeout_s) is None

    def accept(self, count: int, timeout_s: float = 2.0) -> list[bytes]:
        """The payloads of the next ``count`` blocks in order, as the firmware takes them
        (a block of another number, a resend, dropped)."""
        until_s = time.monotonic() + timeout_s
        taken: list[bytes] = []
        while len(taken) < count:
            got = self.next_block(until_s)
            assert got is not None, f"{len(taken)} of {count} blocks came"
            if got[0] == self.expected & 0x0F:
                taken.append(got[1])
                self.expected += 1
        return taken


@pytest.fixture
def link() -> Iterator[tuple[SerialQueue, Board]]:
    host, mcu = socket.socketpair()
    host.setblocking(False)
    queue = SerialQueue(host.fileno())
    try:
        yield queue, Board(mcu)
    finally:
        queue.close()
        host.close()
        mcu.close()


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 2.0) -> None:
    until_s = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < until_s, f"timed out waiting for {what}"
        time.sleep(0.002)


def sleep_until(when_s: float) -> None:
    time.sleep(max(0.0, when_s - time.monotonic()))


def pulled(queue: SerialQueue, count: int, timeout_s: float = 2.0) -> list[tuple[bytes, float]]:
    got: list[tuple[bytes, float]] = []

    def more() -> bool:
        got.extend(queue.pull(4096)[0])
        return len(got) >= count

    wait_for(more, f"{count} responses", timeout_s)
    return got


def until_fault(queue: SerialQueue, timeout_s: float = 2.0) -> tuple[list[bytes], Fault]:
    """The payloads pulled until the fault that ended the link, and that fault."""
    payloads: list[bytes] = []
    fault: list[Fault] = []

    def came() -> bool:
        blocks, one, _ = queue.pull(4096)
        payloads.extend(payload for payload, _ in blocks)
        fault.extend([one] if one is not None else [])
        return bool(fault)

    wait_for(came, "a fault", timeout_s)
    return payloads, fault[0]


def fault_of(queue: SerialQueue, timeout_s: float = 2.0) -> Fault:
    return until_fault(queue, timeout_s)[1]


def signalled(queue: SerialQueue, timeout_s: float) -> bool:
    return bool(select.select([queue.notify_fd], [], [], timeout_s)[0])


def send_each(queue: SerialQueue, count: int) -> list[bytes]:
    """``count`` one-byte messages, each in a block of its own (one send each)."""
    messages = [bytes([i + 1]) for i in range(count)]
    for message in messages:
        queue.send([message])
    return messages


def answered_slowly(queue: SerialQueue, board: Board, start_s: float, count: int) -> None:
    """The board takes ``count`` blocks and answers the first ``SLOW_S`` after ``start_s``
    with a response and its ack: a round trip of ~SLOW_S is measured."""
    board.accept(count)
    sleep_until(start_s + SLOW_S)
    board.write(block(1, b"\x01"), block(1))
    wait_for(lambda: queue.stats()["acked"] == 1, "block 0 acknowledged")
    srtt_s = queue.stats()["srtt_s"]
    assert srtt_s is not None and srtt_s >= SLOW_S * 0.9


# -- the window's rules (ported from the pure-Python SendWindow's tests) ----------------------
def test_an_ack_releases_the_blocks_before_it_and_measures_the_round_trip(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    send_each(queue, 3)
    assert board.accept(3) == [b"\x01", b"\x02", b"\x03"] and queue.in_flight == 3
    board.write(block(1, b"\x07"), block(3))  # a response to block 0 (synced), then an ack
    wait_for(lambda: queue.in_flight == 0, "all three acknowledged")
    stats = queue.stats()
    assert stats["acked"] == 3 and stats["srtt_s"] is not None and stats["inflight_bytes"] == 0
    assert [payload for payload, _ in pulled(queue, 1)] == [b"\x07"]


def test_a_nak_resends_everything_unacknowledged_once(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    start_s = time.monotonic()
    messages = send_each(queue, 4)
    answered_slowly(queue, board, start_s, 4)  # block 0's response and the ack after it
    board.write(block(1), block(1), block(1))  # a nak, and the naks its resend would cause
    assert board.blocks(3) == [(1, messages[1]), (2, messages[2]), (3, messages[3])]
    board.write(block(4))
    wait_for(lambda: queue.in_flight == 0, "the resent blocks acknowledged")
    assert queue.stats()["retransmits"] == 1, "the naks a resend causes are not obeyed"
    assert board.quiet(0.05)


def test_the_ack_after_a_response_is_no_nak(link: tuple[SerialQueue, Board]) -> None:
    """The firmware answers a request, then acknowledges its block with an empty block of
    the same number: with more blocks in flight that ack is no nak, nothing is sent again."""
    queue, board = link
    start_s = time.monotonic()
    send_each(queue, 3)
    answered_slowly(queue, board, start_s, 3)
    board.write(block(2, b"\x02"), block(2))
    wait_for(lambda: queue.stats()["acked"] == 2, "block 1 acknowledged")
    stats = queue.stats()
    assert stats["retransmits"] == 0 and stats["inflight"] == 1
    assert [payload for payload, _ in pulled(queue, 2)] == [b"\x01", b"\x02"]


def test_a_timeout_resends_with_a_doubled_timeout(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    start_s = time.monotonic()
    messages = send_each(queue, 2)
    assert board.blocks(2) == [(0, messages[0]), (1, messages[1])]
    assert board.blocks(2) == [(0, messages[0]), (1, messages[1])]  # the board stays silent
    resent_s = time.monotonic()
    assert RTO_S <= resent_s - start_s < 1.0
    stats = queue.stats()
    assert stats["retransmits"] >= 1 and stats["srtt_s"] is None
    assert stats["rto_s"] == pytest.approx(RTO_S * 2 ** stats["retransmits"])


def test_a_number_never_sent_means_the_mcu_restarted(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    send_each(queue, 5)
    board.accept(5)
    board.write(block(5, b"\x01"))
    wait_for(lambda: queue.in_flight == 0, "five blocks acknowledged")
    send_each(queue, 2)
    board.accept(2)
    board.write(block(0))  # it expects block 0 (16, of 7 sent): it restarted
    payloads, (kind, text) = until_fault(queue)
    assert payloads == [b"\x01"] and kind == "broken" and "restarted" in text


def test_joining_an_mcu_that_served_a_host_before_adopts_its_count(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.send([b"\x42"])
    assert board.blocks(1) == [(0, b"\x42")]
    board.write(block(1))  # a nak that happens to look like an ack of block 0
    board.expected = 1
    assert board.accept(1) == [b"\x42"], "the block again, framed as the MCU's block 1"
    stats = queue.stats()
    assert stats["acked"] == 1 and stats["next_seq"] == 2
    board.write(block(2, b"\x05"))
    wait_for(lambda: queue.in_flight == 0, "the adopted block acknowledged")
    assert [payload for payload, _ in pulled(queue, 1)] == [b"\x05"]


def framings(queue: SerialQueue) -> int:
    """How often the one 6-byte block was framed anew (adopted): blocks written, less the
    first and the resends."""
    stats = queue.stats()
    return int(stats["bytes_sent"]) // 6 - 1 - int(stats["retransmits"])


def test_a_flood_of_empty_blocks_before_the_first_ack_draws_one_resend_per_round_trip(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.send([b"\x01"])
    board.blocks(1)
    flood_s = time.monotonic()
    board.write(block(5) * 100)
    board.expected = 5
    assert board.accept(1) == [b"\x01"]
    assert framings(queue) == 1
    while framings(queue) == 1:  # a round trip later: once more
        assert time.monotonic() < flood_s + 2.0, "no second adoption"
        board.write(block(5))
        time.sleep(0.02)
    assert time.monotonic() - flood_s >= RTO_S and framings(queue) == 2


# -- the send side: bursts, the window, the retransmission timer ------------------------------
def test_a_burst_of_three_blocks_leaves_in_one_write(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    burst = [bytes([i]) * 10 for i in range(11)]  # 5 to a block: 5, 5 and 1
    before = queue.stats()
    queue.send(burst)
    after = queue.stats()
    assert after["writes"] - before["writes"] == 1
    assert after["next_seq"] - before["next_seq"] == 3
    payloads = board.accept(3)
    assert [len(p) for p in payloads] == [50, 50, 10] and b"".join(payloads) == b"".join(burst)
    board.write(block(3, b"\x01"))
    wait_for(lambda: queue.in_flight == 0, "the burst acknowledged")


def test_bytes_beyond_the_window_wait_and_leave_as_acknowledgements_free_room(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    assert queue.window_bytes == 192
    messages = [bytes([i]) * 10 for i in range(30)]
    queue.send(messages)  # blocks of 55, 55, 55 and 25 bytes fill it (190 bytes)
    assert queue.in_flight == 4 and queue.stats()["inflight_bytes"] == 190
    assert queue.queued_bytes == 130 and queue.queued() == messages[17:]
    payloads = board.accept(4)
    board.write(block(4, b"\x01"))  # no call to the queue from here on: its thread refills
    payloads += board.accept(3)
    board.write(block(7))
    assert b"".join(payloads) == b"".join(messages)
    wait_for(lambda: queue.in_flight == 0, "all seven acknowledged")
    assert queue.queued_bytes == 0 and queue.stats()["next_seq"] == 7


def test_blocks_beyond_max_blocks_wait_for_room(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    messages = send_each(queue, 13)
    assert queue.in_flight == 12 and queue.queued() == [messages[12]]
    assert queue.stats()["inflight_bytes"] == 12 * 6
    assert board.accept(12) == messages[:12]
    board.write(block(1, b"\x01"))
    assert board.accept(1) == [messages[12]]
    assert queue.queued() == [] and queue.queued_bytes == 0


def first_repeat(received: list[Block]) -> int | None:
    seen: set[int] = set()
    for index, (seq4, _) in enumerate(received):
        if seq4 in seen:
            return index
        seen.add(seq4)
    return None


def test_retransmission_is_timed_from_the_oldest_unacknowledged_block(
        link: tuple[SerialQueue, Board]) -> None:
    """Blocks keep leaving every 40 ms behind the first while the board stays silent: the
    first one's timeout passes all the same (later blocks do not postpone it), and all in
    flight are resent together, oldest first."""
    queue, board = link
    start_s = time.monotonic()
    queue.send([b"\x01"])
    queue.send([b"\x02"])  # behind the first at once
    received: list[Block] = []
    sent, resent_s = 2, None
    while resent_s is None and time.monotonic() < start_s + 2.0:
        due_s = start_s + 0.04 * (sent - 1) if sent < 12 else start_s + 2.0
        while (got := board.next_block(due_s)) is not None:
            received.append(got)
            if first_repeat(received) is not None:
                resent_s = time.monotonic()
                break
        if resent_s is None and sent < 12:
            sent += 1
            queue.send([bytes([sent])])
    assert resent_s is not None and RTO_S <= resent_s - start_s < 1.0
    first = first_repeat(received)  # the blocks sent before the resend
    assert first is not None and first < 12, "the later blocks postponed the first's timeout"
    received += board.blocks(2 * first - len(received))
    assert received[first:2 * first] == received[:first]  # all of them, together, in order
    assert [seq4 for seq4, _ in received[:first]] == list(range(first))


# -- the receive side: arrival times, signals, faults -----------------------------------------
def test_a_response_is_pulled_with_its_arrival_time(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    written_s = time.monotonic()
    board.write(block(0, b"\x05hello"))
    [(payload, received_s)] = pulled(queue, 1)
    assert payload == b"\x05hello" and written_s <= received_s <= time.monotonic()
    assert queue.bytes_received == len(block(0, b"\x05hello"))
    assert queue.pull(4096) == ([], None, False)


def test_responses_are_signalled_only_when_asked(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.set_notify(False)
    board.write(block(0, b"\x01"))
    wait_for(lambda: queue.bytes_received > 0, "the response read")
    assert not signalled(queue, 0.1)
    assert [payload for payload, _ in queue.pull(4096)[0]] == [b"\x01"]
    size = queue.bytes_received
    board.write(block(0, b"\x02"))
    wait_for(lambda: queue.bytes_received > size, "the second response read")
    assert not signalled(queue, 0.0)
    queue.set_notify(True)  # a response waits: signalled at once
    assert signalled(queue, 0.0)
    assert [payload for payload, _ in queue.pull(4096)[0]] == [b"\x02"]
    assert not signalled(queue, 0.0), "the pull took the signal"
    board.write(block(0, b"\x03"))
    assert signalled(queue, 1.0)
    assert [payload for payload, _ in queue.pull(4096)[0]] == [b"\x03"]


def test_an_ack_timeout_is_signalled_even_with_notify_off(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.set_notify(False)
    queue.ack_timeout_s = 0.2
    assert queue.ack_timeout_s == pytest.approx(0.2)
    start_s = time.monotonic()
    queue.send([b"\x01"])
    assert signalled(queue, 2.0) and time.monotonic() - start_s >= 0.2
    kind, text = fault_of(queue)
    found = re.fullmatch(r"the MCU acknowledged none of 1 blocks for (\d+\.\d\d) s "
                         r"\(it sent nothing meanwhile\)", text)
    assert kind == "broken" and found is not None, text
    assert 0.2 <= float(found.group(1)) < 1.0


def test_garbage_before_a_valid_block_is_skipped(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    damaged = bytearray(block(0, b"\x09\x08"))
    damaged[2] ^= 0x01  # its crc no longer matches
    assert 0x7E not in damaged[:-1]
    board.write(b"\x00\x01noise\xff\x7e" + bytes(damaged) + block(0, b"\x05ok"))
    assert [payload for payload, _ in pulled(queue, 1)] == [b"\x05ok"]
    assert queue.stats()["bad_blocks"] >= 1


def test_send_first_jumps_a_full_window(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    messages = send_each(queue, 12)  # the window is full (max_blocks)
    queue.send([b"\xa1", b"\xa2"])
    queue.send([b"\xb1"], keep=True)  # a request: kept
    queue.send([b"\xb2", b"\xa3"], keep_first=1)
    assert queue.queued() == [b"\xa1", b"\xa2", b"\xb1", b"\xb2", b"\xa3"]
    assert queue.send_first(b"\xee") == [b"\xa1", b"\xa2", b"\xa3"]
    assert queue.queued() == [b"\xb1", b"\xb2"] and queue.queued_bytes == 2
    assert queue.in_flight == 13 and queue.inflight()[-1] == b"\xee"
    assert board.accept(13) == [*messages, b"\xee"]  # written at once, past the window
    board.write(block(13, b"\x01"))
    assert board.accept(1) == [b"\xb1\xb2"], "the kept ones leave once there is room"


def test_the_peer_closing_its_end_is_a_hangup(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    board.sock.close()
    assert signalled(queue, 1.0)
    assert fault_of(queue, 1.0) == ("hangup", "closed")


def test_halt_stops_reading_but_not_writing(link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.halt("an undecodable message")
    board.write(block(0, b"\x05late"))
    time.sleep(0.1)
    assert queue.pull(4096) == ([], None, False), "the halting side knows its fault"
    queue.send([b"\x01"])
    assert board.blocks(1) == [(0, b"\x01")]


def test_close_twice_is_safe_and_nothing_is_written_after(
        link: tuple[SerialQueue, Board]) -> None:
    queue, board = link
    queue.close()
    queue.close()
    queue.send([b"\x01"])
    queue.send_first(b"\x02")
    assert board.quiet(0.2)
    assert queue.bytes_sent == 0 and queue.stats()["writes"] == 0


# -- the thread's own faults, once fixed ---------------------------------------------------------
def test_a_fault_taken_leaves_notify_fd_quiet(link: tuple[SerialQueue, Board]) -> None:
    """A broken link's reader stays registered until it is closed: the signal of its fault
    is taken with it, not left for the event loop to spin on."""
    queue, _ = link
    queue.ack_timeout_s = 0.1
    queue.send([b"\x01"])
    assert fault_of(queue)[0] == "broken"
    assert not signalled(queue, 0.0)


def test_a_hangup_after_halt_does_not_spin_the_thread(link: tuple[SerialQueue, Board]) -> None:
    """A halted link does not poll the device (a hung-up one reports POLLHUP whatever is
    asked: the thread would spin)."""
    queue, board = link
    queue.halt("an undecodable message")
    wakes = queue.stats()["wakes"]
    board.sock.close()
    time.sleep(0.2)
    assert queue.stats()["wakes"] - wakes < 100


def test_at_most_fifteen_blocks_are_in_flight(link: tuple[SerialQueue, Board]) -> None:
    """A 4-bit acknowledgement tells 16 blocks in flight from none: the window fills 12, three
    send_first may go past it, and a fourth is refused before anything is dropped."""
    queue, _ = link
    with pytest.raises(ValueError):
        SerialQueue(queue.notify_fd, 192, 13)
    send_each(queue, 12)
    for k in range(3):
        queue.send_first(bytes([0x30 + k]))
    queue.send([b"\x05"])
    assert queue.in_flight == 15 and queue.queued() == [b"\x05"]
    with pytest.raises(BufferError):
        queue.send_first(b"\x40")
    assert queue.in_flight == 15 and queue.queued() == [b"\x05"], "nothing dropped"
