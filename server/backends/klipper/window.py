"""Acknowledgement and retransmission of host-to-MCU message blocks (pure).

Every block the host sends carries a 4-bit sequence number; the MCU answers each block it
accepts with the next sequence number it expects (in an empty "ack" block or in any response),
and discards blocks out of order, answering those with the number it still expects (a "nak").
A block that draws a response is acknowledged twice: by the response, then by the empty block
that follows it, so a nak is an empty block repeating the number of the last *empty* one (as
Klipper's host tells them apart), not merely one that acknowledges nothing new.
The host keeps the blocks not yet acknowledged, at most ``max_blocks`` of them and
``window_bytes`` bytes (the MCU's ``RECEIVE_WINDOW``), and sends them all again from the first
unacknowledged one when a nak arrives or the retransmission timeout passes (doubling each time,
reset by a fresh round-trip measurement); naks are ignored for two round trips after a resend
(the duplicates a resend causes draw naks of their own). A sequence number that cannot be an
answer to what was sent means the MCU restarted (:class:`SequenceError`), except before the
first acknowledgement: an MCU that served a host before keeps its count, and the host adopts it
(as Klipper's host does), at most once per retransmission timeout (a board that floods empty
blocks draws no flood of resends).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from server.backends.klipper.codec import SEQ_MASK, frame

MIN_RTO_S = 0.025
MAX_RTO_S = 2.0


class SequenceError(Exception):
    """The MCU acknowledged blocks that were never sent (it restarted)."""


@dataclass(slots=True)
class _Sent:
    seq: int
    payload: bytes
    block: bytes
    sent_s: float
    retransmitted: bool = False


class SendWindow:
    """The host side of the sequence window; see the module docstring."""

    def __init__(self, window_bytes: int = 192, max_blocks: int = 12) -> None:
        self.window_bytes = window_bytes
        self.max_blocks = max_blocks
        self.next_seq = 0  # 64-bit count of blocks made
        self.acked = 0  # the first block not yet acknowledged
        self.inflight: deque[_Sent] = deque()
        self.bytes_in_flight = 0  # the blocks' bytes in inflight (kept, not summed per call)
        self.rto_s = MIN_RTO_S * 4
        self.srtt_s: float | None = None
        self.retransmits = 0
        self.synced = False  # a response to one of our blocks was seen (the first command
        # always draws one: an empty block before it is a nak whatever its number)
        self._ignore_naks_until_s = 0.0
        self._last_empty = 0  # the number the last empty block acknowledged (64-bit)

    def can_send(self, size_bytes: int) -> bool:
        return (len(self.inflight) < self.max_blocks
                and self.bytes_in_flight + size_bytes <= self.window_bytes)

    def make_block(self, payload: bytes, now_s: float) -> bytes:
        """Frame ``payload`` with the next sequence number and keep it until acknowledged."""
        block = frame(self.next_seq, payload)
        self.inflight.append(_Sent(self.next_seq, payload, block, now_s))
        self.bytes_in_flight += len(block)
        self.next_seq += 1
        return block

    @property
    def recovering(self) -> bool:
        """The oldest block in flight was sent again: its timeout is judged on time (a second
        loss must not wait for anything)."""
        return bool(self.inflight) and self.inflight[0].retransmitted

    def deadline_s(self) -> float | None:
        """When the oldest unacknowledged block times out (None if nothing is in flight)."""
        return self.inflight[0].sent_s + self.rto_s if self.inflight else None

    def on_block(self, seq4: int, empty: bool, now_s: float, timed: bool = True) -> list[bytes]:
        """A block from the MCU acknowledging up to ``seq4``; blocks to send again (a nak).
        ``timed``: read as it arrived (else it may have waited: it measures no round trip)."""
        ahead = (seq4 - self.acked) & SEQ_MASK
        rseq = self.acked + ahead
        if not self.synced:
            if empty or rseq > self.next_seq:  # a nak: an MCU that ran before; adopt its count
                if now_s < self._ignore_naks_until_s:  # once a round trip, not per block
                    return []
                self._ignore_naks_until_s = now_s + self.rto_s
                return self._adopt(rseq, now_s)
            self.synced = rseq > self.acked
        if rseq > self.next_seq:
            raise SequenceError(f"the MCU expects block {seq4} of 16, never sent: it restarted")
        if rseq > self.acked:
            self._acknowledge(rseq, now_s, timed)
        if not empty:
            return []
        if rseq > self._last_empty:  # an ack (perhaps after the response that acked first)
            self._last_empty = rseq
            return []
        if self.inflight and now_s >= self._ignore_naks_until_s:
            return self._resend(now_s)
        return []

    def _adopt(self, rseq: int, now_s: float) -> list[bytes]:
        """Number from the MCU's expected block on (a first connection to an MCU that talked
        to a host before); what was in flight is framed again with the new numbers."""
        payloads = [sent.payload for sent in self.inflight]
        self.inflight.clear()
        self.bytes_in_flight = 0
        self.acked = self.next_seq = self._last_empty = rseq
        return [self.make_block(payload, now_s) for payload in payloads]

    def on_timer(self, now_s: float) -> list[bytes]:
        """Blocks to send again if the oldest one timed out."""
        deadline = self.deadline_s()
        if deadline is None or now_s < deadline:
            return []
        self.rto_s = min(MAX_RTO_S, self.rto_s * 2)
        return self._resend(now_s)

    def _acknowledge(self, rseq: int, now_s: float, timed: bool) -> None:
        while self.inflight and self.inflight[0].seq < rseq:
            sent = self.inflight.popleft()
            self.bytes_in_flight -= len(sent.block)
            if timed and not sent.retransmitted:
                self._measure(now_s - sent.sent_s)
        self.acked = rseq

    def _measure(self, rtt_s: float) -> None:
        self.srtt_s = rtt_s if self.srtt_s is None else 0.875 * self.srtt_s + 0.125 * rtt_s
        self.rto_s = min(MAX_RTO_S, max(MIN_RTO_S, 3.0 * self.srtt_s))

    def _resend(self, now_s: float) -> list[bytes]:
        """Everything unacknowledged again. The duplicates a resend causes draw naks of their
        own within a round trip: naks are ignored for two round trips."""
        self.retransmits += 1
        self._ignore_naks_until_s = now_s + 2.0 * max(self.srtt_s or 0.0, MIN_RTO_S / 5)
        for sent in self.inflight:
            sent.sent_s, sent.retransmitted = now_s, True
        return [sent.block for sent in self.inflight]
