"""Fewer wake-ups (issue #26, part W): while the step generator ticks, the Klipper link reads
the MCU at the ticks' samples, with no reader in the event loop (every wake-up of the process
costs CPU); idle, or while an answer is awaited, it reads as data arrives. A board's shutdown
mid-motion is read, and acted on, at the next sample; an idle board's at once."""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any

import pytest

from server.backends.klipper import mcu as mcu_module
from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.link import Link
from tests.integration.test_klipper_faults import wait_for_alarm
from tests.support.helpers import submit_all
from tests.support.klipper_machine import configured_link, klipper_machine
from tests.support.virtual_mcu import VirtualMcu

LASER = {"pin": "PA8"}


def registered(link: Link) -> bool:
    """Whether the event loop watches the link's device (asks the loop's selector itself)."""
    selector = asyncio.get_running_loop()._selector  # type: ignore[attr-defined]
    fd = link._fd
    assert fd is not None
    try:
        key = selector.get_key(fd)
    except KeyError:
        return False
    return key.data[0] is not None  # (reader, writer) handles


class Deliveries:
    """Which messages the link delivered, and whether from a drain of the device (a sample's,
    the retransmission timer's: between sparse samples it judges what a sample sent, or a
    window's refill), not by the event loop's reader."""

    def __init__(self, link: Link) -> None:
        self.seen: list[tuple[str, bool, float]] = []
        self.in_sample = False
        drain, deliver = link._drain, link._on_message

        def drained() -> None:
            self.in_sample = True
            try:
                drain()
            finally:
                self.in_sample = False

        def delivered(name: str, params: Any, now_s: float) -> None:
            self.seen.append((name, self.in_sample, now_s))
            deliver(name, params, now_s)

        link._drain = drained  # type: ignore[method-assign]
        link._on_message = delivered

    def first(self, name: str) -> tuple[bool, float]:
        for seen, in_sample, now_s in self.seen:
            if seen == name:
                return in_sample, now_s
        raise AssertionError(f"no {name} delivered: {[s[0] for s in self.seen]}")


async def test_the_link_reads_at_the_samples_while_ticking_and_as_data_arrives_when_idle(
        mcu: VirtualMcu, monkeypatch: pytest.MonkeyPatch) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        link = backend.mcu.link
        assert link.watched and registered(link), "idle: read as data arrives"
        monkeypatch.setattr(mcu_module, "BUSY_POLL_S", 10.0)  # no clock poll meanwhile
        backend.mcu.poll_s = 10.0
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])  # 2 s of cutting
        await asyncio.sleep(0.6)  # past the poll that was due (its answer is awaited)
        drains = link.drains
        unwatched = 0
        for _ in range(20):
            await asyncio.sleep(0.01)
            unwatched += not link.watched and not registered(link)
        assert unwatched >= 18, "moving: no reader in the event loop"
        assert link.drains - drains >= 2, "the samples read the acknowledgements"
        assert link.window.retransmits == 0

        deliveries = Deliveries(link)
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        sent_s = time.monotonic()
        took_s = await wait_for_alarm(app)
        in_sample, read_s = deliveries.first("shutdown")
        assert in_sample, "read at a sample (or its blocks' timer), not by a reader"
        assert read_s - sent_s < 0.2  # a sample (at most the hold-back: 50 ms here) apart
        assert took_s < 1.0
        assert "the MCU shut down: Rescheduled timer in the past" in app.kernel.alarm_message
        assert mcu.output_events("PA8")[-1][1] == 0


async def test_an_idle_board_s_shutdown_is_read_at_once_without_a_tick(
        mcu: VirtualMcu) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        machine = app.kernel.machine
        backend = machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        await submit_all(app, ["G1 X10 F6000"])
        await machine.wait_idle()
        for _ in range(200):  # the steps run out a lead later, then the ticks stop
            if machine.stepgen.can_sleep and not backend.mcu.link.sampling:
                break
            await asyncio.sleep(0.01)
        link = backend.mcu.link
        assert not link.sampling and link.watched and registered(link)
        deliveries = Deliveries(link)
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        sent_s = time.monotonic()
        await wait_for_alarm(app)
        in_sample, read_s = deliveries.first("shutdown")
        assert not in_sample and read_s - sent_s < 0.2  # a few ms here
        assert "Rescheduled timer in the past" in app.kernel.alarm_message


async def burst(mcu: VirtualMcu, monkeypatch: pytest.MonkeyPatch,
                count: int = 600) -> tuple[Link, dict[str, int], int]:
    """``count`` small messages sent at once to ``mcu`` by a link whose owner samples (and no
    sample comes: only the event loop reads); checks they all arrive once, in order. Returns
    the link, how many times the event loop called each of its callbacks meanwhile and how
    many blocks it made."""
    calls: dict[str, int] = {}
    for name in ("_on_readable", "_on_timer", "_on_refill"):  # every way the loop calls in
        original = getattr(Link, name)

        def counted(link: Link, original: Any = original, name: str = name) -> None:
            calls[name] = calls.get(name, 0) + 1
            original(link)

        monkeypatch.setattr(Link, name, counted)
    async with configured_link(mcu) as (link, encode):
        first_block = link.window.next_seq
        calls.clear()
        link.send(*[encode.encode("update_digital_out", oid=0, value=k % 2)
                    for k in range(count)])
        for _ in range(1000):
            if not link.queued_bytes and not link.window.inflight:
                break
            await asyncio.sleep(0.01)
        assert not link.queued_bytes and not link.window.inflight
        updates = [p["value"] for _, name, p in mcu.commands if name == "update_digital_out"]
        assert updates == [k % 2 for k in range(count)], "every message once, in order"
        return link, calls, link.window.next_seq - first_block


async def test_messages_waiting_for_room_leave_at_one_read_a_window_not_one_an_ack(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """While the owner samples, a burst many windows long leaves as the window's
    acknowledgements have had time to come: the event loop calls the link about once a window
    (192 bytes: three blocks), not once for each block's acknowledgement (and again for the
    rest of it; main: 29-30 calls for 11 windows)."""
    mcu = VirtualMcu(baud=250000).start()  # a UART's pace: each acknowledgement in its turn
    try:
        link, calls, blocks = await burst(mcu, monkeypatch)
    finally:
        mcu.stop()
    windows, loop_calls = math.ceil(blocks / 3), sum(calls.values())
    assert windows >= 10
    assert link.window.retransmits == 0 and mcu.naks_sent == 0
    assert loop_calls <= 2 * windows, f"{loop_calls} calls for {windows} windows"


async def test_a_board_slower_than_its_wire_has_its_acknowledgements_read_as_they_come(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A board that takes eight times the wire's time (here: its UART at 31,250 baud, the link
    told 250,000) has acknowledged nothing when the window's read comes: its acknowledgements
    are then read as they arrive (the reader, not only the retransmission timer), and the
    burst still gets through, once and in order (with resends, as on main: a window's round
    trip there is longer than the 25 ms floor of the retransmission timeout)."""
    mcu = VirtualMcu(baud=31250).start()
    try:
        link, calls, blocks = await burst(mcu, monkeypatch, count=150)
    finally:
        mcu.stop()
    assert calls.get("_on_refill", 0) >= 1, calls
    assert calls.get("_on_readable", 0) >= 1, f"read as they came: {calls}"
    assert blocks >= 8 and not link._slow, "the window moved: back to one read a window"


async def test_a_busy_board_s_clock_poll_rides_the_steps_without_a_timer_of_its_own(
        mcu: VirtualMcu, monkeypatch: pytest.MonkeyPatch) -> None:
    """While steps flow, a clock poll leaves with the first block of steps a period after the
    last one: the watch sets no timer of its own to wait for that period (one wake-up less a
    poll), and the polls still come a period apart, each in a block with steps."""
    waits: list[float | None] = []
    wait = asyncio.wait

    async def counted(*args: Any, **kwargs: Any) -> Any:
        waits.append(kwargs.get("timeout"))
        return await wait(*args, **kwargs)

    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        board = backend.mcu
        sent: list[tuple[float, bytes]] = []
        write = board.link._write

        def recorded(data: bytes, flush: bool = True) -> None:
            sent.append((time.monotonic(), data))
            write(data, flush)

        monkeypatch.setattr(board.link, "_write", recorded)
        monkeypatch.setattr(mcu_module.asyncio, "wait", counted)
        await submit_all(app, ["G1 X100 F3000"])  # 2 s of motion
        await asyncio.sleep(0.6)
        polls_before, waits_before = board._polls, len(waits)  # noqa: SLF001
        since_s = time.monotonic()
        await asyncio.sleep(1.2)
        assert board.busy
        polls = board._polls - polls_before  # noqa: SLF001
        timed = [t for t in waits[waits_before:] if t is not None]
        assert timed == [], "no timer of the watch's own while busy"
        assert 2 <= polls <= 4, polls  # every 0.4 s
        blocks = []
        for sent_s, data in sent:  # a write: whole blocks (length, sequence, payload, crc, sync)
            while sent_s >= since_s and data:
                blocks.append([name for name, _ in board.dictionary.decode(data[2:data[0] - 3])])
                data = data[data[0]:]
        polled = [names for names in blocks if "get_clock" in names]
        assert polled and all("queue_step" in names for names in polled), polled
        await app.kernel.machine.wait_idle()
