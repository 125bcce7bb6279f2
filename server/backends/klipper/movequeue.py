"""The MCU's move queue, seen from the host: messages leave in order while it has room.

What has room leaves in one burst, which the link packs into as few blocks as fit; the
messages that would only part-fill the burst's last block wait while none of them is urgent
(fewer, fuller blocks: a block costs 5 bytes besides its messages).
Every ``queue_step`` and scheduled output takes one of the MCU's ``move_count`` slots until
the MCU has reached it. The host counts a slot as taken from sending the message until its
clock has passed (plus 1 ms, the clock fit's possible lead over the MCU's own: ``_movequeue.c``'s
``QUEUE_MARGIN_S``), so the queue never overflows. A message that would arrive less than 2 ms
(``LATE_MARGIN_S``) before it is due is never sent: the caller halts instead (a late step is
worse than none). The queue and its count are compiled, as klippy's steppersync.
"""

from __future__ import annotations

from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.mcu import Mcu
from server.backends.klipper.stepcore import MoveQueueCore


class MoveQueue(MoveQueueCore):
    """Messages waiting for the MCU, each with the slot it takes (if any) and when it is due
    (compiled: ``_movequeue.c``, which has :meth:`add`, :meth:`extend`, :meth:`turn`,
    :meth:`full`, :meth:`busy`, :meth:`drop`, :meth:`free_slots` and the counts
    ``waiting`` and ``in_use``)."""

    __slots__ = ()

    def __init__(self) -> None:
        super().__init__(PAYLOAD_MAX)

    def pump(self, mcu: Mcu, now: float, hold_after: float | None = None) -> float | None:
        """Send what the queue has room for at MCU clock ``now``, all in one burst (the link
        packs it into as few blocks as fit); returns how many ms late the next message would
        be (nothing more is sent), or None. ``hold_after``: an MCU clock; the messages of a
        last block not filled wait while none of them is due by it (the next burst will share
        their block), the blocks before it go."""
        freq = mcu.clock.freq_hz if mcu.clock else 0.0
        burst, late_ms = self.pump_burst(mcu.move_count, now, freq, hold_after)
        if burst:
            mcu.link.send(*burst)
        return late_ms
