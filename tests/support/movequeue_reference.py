"""The move queue's bookkeeping in plain Python, the oracle the tests hold the compiled queue
(``_movequeue.c``) to: the same bursts, lateness, turns and counts for any sequence of calls.
It is the Python the product ran before the queue was compiled."""

from __future__ import annotations

import heapq
from collections import deque
from typing import Protocol

from server.backends.klipper.codec import PAYLOAD_MAX

LATE_MARGIN_S = 0.002
QUEUE_MARGIN_S = 0.001


class Link(Protocol):
    def send(self, *messages: bytes) -> None: ...


class Clock(Protocol):
    freq_hz: float


class Mcu(Protocol):
    move_count: int
    link: Link
    clock: Clock | None


class ReferenceMoveQueue:
    """Messages waiting for the MCU, each with the slot it takes (if any) and when it is due."""

    def __init__(self) -> None:
        self.waiting: deque[tuple[bytes, int | None, int]] = deque()  # msg, slot until, due
        self.in_use: list[int] = []  # a heap of the clocks the taken slots free at

    def add(self, message: bytes, until: int | None, due: int) -> None:
        """Queue ``message``; ``until`` is the MCU clock its slot frees at (None: no slot)."""
        self.waiting.append((message, until, due))

    def extend(self, messages: list[tuple[bytes, int, int]]) -> None:
        """Queue ``(message, slot until, due)`` triples (each as :meth:`add`)."""
        self.waiting.extend(messages)

    def pump(self, mcu: Mcu, now: float, hold_after: float | None = None) -> float | None:
        """As :meth:`server.backends.klipper.movequeue.MoveQueue.pump`."""
        freq = mcu.clock.freq_hz if mcu.clock else 0.0
        in_use, waiting = self.in_use, self.waiting
        freed = now - QUEUE_MARGIN_S * freq  # slots freed are counted free (see turn)
        while in_use and in_use[0] <= freed:
            heapq.heappop(in_use)
        ready = len(waiting) if hold_after is None else self._ready(hold_after)
        if not ready:
            return None
        late = now + LATE_MARGIN_S * freq
        burst: list[bytes] = []
        late_ms: float | None = None
        while waiting and len(burst) < ready:
            message, until, due = waiting[0]
            if until is not None:
                if len(in_use) >= mcu.move_count:
                    break
                if due < late:
                    late_ms = (late - due) / freq * 1e3 if freq else 0.0
                    break
                heapq.heappush(in_use, until)
            waiting.popleft()
            burst.append(message)
        if burst:
            mcu.link.send(*burst)
        return late_ms

    def _ready(self, hold_after: float) -> int:
        """How many waiting messages go now: all if the last block they fill (packed in order,
        as the link does) has one due by ``hold_after``, else those of the blocks before it."""
        ready, fill, due_soon = 0, 0, False
        for index, (message, _, due) in enumerate(self.waiting):
            if fill + len(message) > PAYLOAD_MAX:  # the block before is full: it goes
                ready, fill, due_soon = index, 0, False
            fill += len(message)
            due_soon = due_soon or due <= hold_after
        return len(self.waiting) if due_soon else ready

    def turn(self, move_count: int, hold_ticks: float, freq_hz: float) -> float | None:
        """The MCU clock at which :meth:`pump` (with ``hold_after`` ``hold_ticks`` ahead) may
        send more of what waits: when a slot frees if the move queue is full, else when the
        first waiting message comes within ``hold_ticks`` of its time; None if nothing waits."""
        if not self.waiting:
            return None
        if self.full(move_count):
            return self.in_use[0] + QUEUE_MARGIN_S * freq_hz
        return min(due for _, _, due in self.waiting) - hold_ticks

    def full(self, move_count: int) -> bool:
        """Whether every slot of the MCU's move queue is taken (as last counted)."""
        return len(self.in_use) >= move_count

    def busy(self, now: float) -> bool:
        """Whether a message waits or a slot is still taken at MCU clock ``now``."""
        return bool(self.waiting) or any(until > now for until in self.in_use)
