"""The move queue's bursts: messages not yet urgent wait to share a block (pure)."""

from __future__ import annotations

from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.movequeue import MoveQueue

HZ = 1_000_000.0  # the late margin is 2,000 ticks


class Link:
    def __init__(self) -> None:
        self.bursts: list[list[bytes]] = []

    def send(self, *messages: bytes) -> None:
        self.bursts.append(list(messages))


class Mcu:
    """What the queue reads of an MCU: its clock fit, move queue size and link."""

    def __init__(self) -> None:
        self.clock = ClockSync(HZ)
        self.move_count = 100
        self.link = Link()


def queue_of(dues: list[int], size: int = 7) -> MoveQueue:
    queue = MoveQueue()
    for due in dues:
        queue.add(bytes(size), due, due)
    return queue


def test_messages_due_after_the_horizon_wait_until_one_is_due_by_it() -> None:
    mcu = Mcu()
    queue = queue_of([50_000, 60_000, 70_000])
    assert queue.pump(mcu, 0.0, hold_after=40_000.0) is None  # type: ignore[arg-type]
    assert mcu.link.bursts == [] and len(queue.waiting) == 3
    queue.add(bytes(7), None, 45_000)  # a dir change due with a later step, say
    queue.pump(mcu, 0.0, hold_after=40_000.0)  # type: ignore[arg-type]
    assert mcu.link.bursts == []
    queue.pump(mcu, 10_000.0, hold_after=50_000.0)  # type: ignore[arg-type]
    assert [len(burst) for burst in mcu.link.bursts] == [4], "all of it, in one burst"


def test_a_message_due_by_the_horizon_anywhere_in_the_queue_sends_all_before_it() -> None:
    """Messages leave in order: one due soon behind others that could wait sends them all."""
    mcu = Mcu()
    queue = queue_of([90_000, 95_000, 30_000])
    queue.pump(mcu, 0.0, hold_after=40_000.0)  # type: ignore[arg-type]
    assert [len(burst) for burst in mcu.link.bursts] == [3] and not queue.waiting


def test_full_blocks_leave_at_once_and_the_part_filled_last_one_waits_unless_due() -> None:
    mcu = Mcu()
    per_block = PAYLOAD_MAX // 7
    queue = queue_of([100_000 + k for k in range(per_block + 3)])
    queue.pump(mcu, 0.0, hold_after=40_000.0)  # type: ignore[arg-type]
    assert [len(burst) for burst in mcu.link.bursts] == [per_block] and len(queue.waiting) == 3
    queue.add(bytes(7), 50_000, 50_000)  # due soon, in the last block: it goes with it
    queue.pump(mcu, 10_000.0, hold_after=60_000.0)  # type: ignore[arg-type]
    assert [len(burst) for burst in mcu.link.bursts] == [per_block, 4] and not queue.waiting


def test_without_a_horizon_everything_with_room_leaves() -> None:
    mcu = Mcu()
    queue = queue_of([90_000, 95_000])
    queue.pump(mcu, 0.0)  # type: ignore[arg-type]
    assert [len(burst) for burst in mcu.link.bursts] == [2]


def test_slots_freed_count_free_even_when_nothing_is_ready_to_go() -> None:
    """A sample whose held messages are not due yet still frees the slots whose moves ran: a
    stale full queue would ask for a sample at a turn long past (ticks back at flush rate)."""
    mcu = Mcu()
    mcu.move_count = 2
    queue = queue_of([10_000, 20_000])
    queue.pump(mcu, 0.0)  # type: ignore[arg-type]
    assert queue.full(mcu.move_count)
    queue.add(bytes(7), 500_000, 500_000)  # held: not due by the horizon
    assert queue.pump(mcu, 100_000.0, hold_after=200_000.0) is None  # type: ignore[arg-type]
    assert len(queue.waiting) == 1 and not queue.full(mcu.move_count)
    turn = queue.turn(mcu.move_count, 100_000.0, HZ)
    assert turn == 400_000.0, "its own turn, not the freed slot's"
