"""The move queue's bursts: messages not yet urgent wait to share a block (pure)."""

from __future__ import annotations

from typing import Any

from hypothesis import example, given, settings
from hypothesis import strategies as st

from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.movequeue import MoveQueue
from tests.support.movequeue_reference import ReferenceMoveQueue

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
    assert mcu.link.bursts == [] and queue.waiting == 3
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
    assert [len(burst) for burst in mcu.link.bursts] == [per_block] and queue.waiting == 3
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
    assert queue.waiting == 1 and not queue.full(mcu.move_count)
    turn = queue.turn(mcu.move_count, 100_000.0, HZ)
    assert turn == 400_000.0, "its own turn, not the freed slot's"


class Recording:
    def __init__(self) -> None:
        self.bursts: list[tuple[bytes, ...]] = []

    def send(self, *messages: bytes) -> None:
        self.bursts.append(messages)


@given(st.lists(st.one_of(
    st.tuples(st.just("add"), st.sampled_from([1, 2, 7, 13, 20, 29, 30, 59]), st.booleans(),
              st.integers(0, 60_000)),
    st.tuples(st.just("pump"), st.integers(0, 5_000), st.integers(0, 20_000), st.booleans()),
    st.tuples(st.just("move_count"), st.integers(1, 6)),
), max_size=80))
@example([("add", 30, True, 50_000), ("add", 29, True, 50_000), ("add", 7, True, 50_000),
          ("pump", 0, 1_000, True)])  # a block filled to the byte, then one that waits
@example([("add", 7, True, 2_000), ("pump", 0, 0, False)])  # due exactly at the late margin
@example([("move_count", 1), ("add", 7, True, 5_000), ("pump", 0, 0, False),
          ("add", 7, True, 9_000), ("pump", 6_000, 0, False)])  # a slot freed exactly now
@example([("move_count", 2), ("add", 7, True, 5_000), ("add", 7, True, 3_000),
          ("add", 7, True, 4_000), ("add", 7, True, 8_000), ("pump", 0, 0, False),
          ("pump", 4_000, 0, False), ("pump", 1_000, 0, False)])  # slots free in clock order
@example([("move_count", 6), ("add", 7, True, 11_000), ("add", 7, True, 15_000),
          ("add", 7, True, 12_000), ("add", 7, True, 16_000), ("add", 7, True, 13_000),
          ("pump", 0, 0, False), ("pump", 12_000, 0, False), ("pump", 1_500, 0, False)])
@settings(max_examples=500, deadline=None)
def test_the_compiled_queue_does_what_the_python_one_did(calls: list[tuple[Any, ...]]) -> None:
    """Any sequence of messages (with or without a slot), pumps (with or without a horizon)
    and move-queue sizes: the same bursts, the same lateness, turns, counts and fullness as
    the Python queue the product ran before (tests/support/movequeue_reference.py)."""
    compiled, reference = MoveQueue(), ReferenceMoveQueue()
    mcus = [Mcu(), Mcu()]
    links = [Recording(), Recording()]
    for mcu, link in zip(mcus, links, strict=True):
        mcu.move_count, mcu.link = 3, link  # type: ignore[assignment]
    now = 0
    for call in calls:
        if call[0] == "add":
            _, size, slot, due = call
            message = bytes([size]) * size
            compiled.add(message, due if slot else None, due)
            reference.add(message, due if slot else None, due)
        elif call[0] == "pump":
            _, step, horizon, held = call
            now += step
            hold_after = float(now + horizon) if held else None
            late = [queue.pump(mcu, float(now), hold_after)  # type: ignore[arg-type]
                    for queue, mcu in ((compiled, mcus[0]), (reference, mcus[1]))]
            assert late[0] == late[1]
        else:
            mcus[0].move_count = mcus[1].move_count = call[1]
        count = mcus[0].move_count
        assert links[0].bursts == links[1].bursts
        assert compiled.waiting == len(reference.waiting)
        assert compiled.in_use == len(reference.in_use)
        assert compiled.full(count) == reference.full(count)
        assert compiled.turn(count, 50_000.0, HZ) == reference.turn(count, 50_000.0, HZ)
        assert compiled.busy(float(now)) == reference.busy(float(now))
