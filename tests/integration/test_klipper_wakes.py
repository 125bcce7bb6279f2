"""Fewer wake-ups (issues #26 and #41): the Klipper link's own thread reads the MCU, stamps
each block with its arrival time, acknowledges, resends and refills the window, so while the
step generator ticks the event loop is woken for nothing of the link's: the responses wait for
the next sample (a riding clock poll's answer too: its arrival time was stamped by the
thread); idle, or while another answer is awaited, each response is signalled at once. A
board's shutdown mid-motion is read, and acted on, at the next sample; an idle board's at
once."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
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


class Deliveries:
    """Which messages the link delivered, and whether at a sample (not woken by its thread)."""

    def __init__(self, link: Link) -> None:
        self.seen: list[tuple[str, bool, float]] = []
        self.in_sample = False
        sample, deliver = link.sample, link._on_message

        def sampled() -> None:
            self.in_sample = True
            try:
                sample()
            finally:
                self.in_sample = False

        def delivered(name: str, params: Any, now_s: float) -> None:
            self.seen.append((name, self.in_sample, time.monotonic()))
            deliver(name, params, now_s)

        link.sample = sampled  # type: ignore[method-assign]
        link._on_message = delivered

    def first(self, name: str) -> tuple[bool, float]:
        for seen, in_sample, now_s in self.seen:
            if seen == name:
                return in_sample, now_s
        raise AssertionError(f"no {name} delivered: {[s[0] for s in self.seen]}")


async def test_a_moving_board_wakes_the_event_loop_for_nothing_of_the_link_s(
        mcu: VirtualMcu) -> None:
    """Two seconds of cutting, the clock polled every 0.4 s meanwhile: the thread signals
    nothing (acknowledgements and the window are its own, the polls' answers wait for the
    samples), and a shutdown mid-motion is read at the next sample."""
    async with klipper_machine(mcu, laser=LASER) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        link, board = backend.mcu.link, backend.mcu
        assert link.signalled, "idle: each response signalled as it arrives"
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])  # 2 s of cutting
        await asyncio.sleep(0.3)
        wakes, polls, blocks = link.wakes, board._polls, mcu.blocks_received  # noqa: SLF001
        await asyncio.sleep(1.2)
        assert board.busy and link.sampling
        polled = board._polls - polls  # noqa: SLF001
        assert polled >= 2, "the clock was polled meanwhile"
        assert mcu.blocks_received - blocks >= 5, "steps flowed meanwhile"
        assert link.wakes == wakes, "nothing woke the event loop for the link"
        assert link.retransmits == 0

        deliveries = Deliveries(link)
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        sent_s = time.monotonic()
        took_s = await wait_for_alarm(app)
        in_sample, read_s = deliveries.first("shutdown")
        assert in_sample, "read at a sample, not signalled"
        assert read_s - sent_s < 0.25  # a sample apart at most
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
        assert not link.sampling and link.signalled
        deliveries = Deliveries(link)
        wakes = link.wakes
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        sent_s = time.monotonic()
        await wait_for_alarm(app)
        in_sample, read_s = deliveries.first("shutdown")
        assert not in_sample and link.wakes > wakes and read_s - sent_s < 0.2  # a few ms here
        assert "Rescheduled timer in the past" in app.kernel.alarm_message


async def burst(mcu: VirtualMcu, count: int = 600) -> tuple[Link, int, dict[str, Any]]:
    """``count`` small messages sent at once to ``mcu`` by a link whose owner samples (and no
    sample comes); checks they all arrive once, in order. Returns the link, how many times the
    event loop was woken for it meanwhile, and its thread's counts."""
    async with configured_link(mcu) as (link, encode):
        await asyncio.sleep(0.05)  # what the configuration's turn of the loop had signalled
        wakes, before = link.wakes, link.stats()
        link.send(*[encode.encode("update_digital_out", oid=0, value=k % 2)
                    for k in range(count)])
        for _ in range(1000):
            if not link.queued_bytes and not link.in_flight:
                break
            await asyncio.sleep(0.01)
        assert not link.queued_bytes and not link.in_flight
        updates = [p["value"] for _, name, p in mcu.commands if name == "update_digital_out"]
        assert updates == [k % 2 for k in range(count)], "every message once, in order"
        after = link.stats()
        return link, link.wakes - wakes, {k: after[k] - before[k] for k in ("next_seq", "wakes")}


async def test_messages_waiting_for_room_leave_as_the_thread_reads_the_acknowledgements() -> None:
    """A burst many windows long (192 bytes: three blocks) at a UART's pace leaves as the
    acknowledgements come, which the link's thread reads: the event loop is not woken once
    for it (before the thread: once a window at best, once a block at worst)."""
    mcu = VirtualMcu(baud=250000).start()  # a UART's pace: each acknowledgement in its turn
    try:
        link, wakes, counts = await burst(mcu)
    finally:
        mcu.stop()
    assert counts["next_seq"] >= 30, counts
    assert wakes == 0
    assert link.retransmits == 0 and mcu.naks_sent == 0
    # the thread's: a block and its acknowledgement in pieces, 4-6 wakes a block here, 9 once in
    # CI beside the rest of the suite; a thread that spun would wake thousands of times
    assert counts["wakes"] <= 16 * counts["next_seq"], counts


async def test_a_board_slower_than_its_wire_still_gets_every_message_once_in_order() -> None:
    """A board that takes eight times the wire's time (its UART at 31,250 baud, the link told
    250,000): the window's round trip is longer than the 25 ms floor of the retransmission
    timeout, blocks are resent, and the burst still gets through once and in order."""
    mcu = VirtualMcu(baud=31250).start()
    try:
        _, wakes, counts = await burst(mcu, count=150)
    finally:
        mcu.stop()
    assert counts["next_seq"] >= 8 and wakes == 0


class Sends:
    """The messages of each call to the link's thread's ``send`` (a proxy in its place)."""

    def __init__(self, link: Link) -> None:
        self.calls: list[tuple[float, Sequence[bytes]]] = []
        self._queue = link._queue
        link._queue = self  # type: ignore[assignment]

    def send(self, messages: Sequence[bytes], keep: bool = False, keep_first: int = 0) -> None:
        self.calls.append((time.monotonic(), messages))
        assert self._queue is not None
        self._queue.send(messages, keep, keep_first)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._queue, name)


async def test_a_busy_board_s_clock_poll_rides_the_steps_without_a_timer_of_its_own(
        mcu: VirtualMcu, monkeypatch: pytest.MonkeyPatch) -> None:
    """While steps flow, a clock poll leaves with the first block of steps a period after the
    last one: the watch sets no timer of its own to wait for that period (one wake-up less a
    poll), and the polls still come a period apart, each first in a burst of steps."""
    waits: list[float | None] = []
    wait = asyncio.wait

    async def counted(*args: Any, **kwargs: Any) -> Any:
        waits.append(kwargs.get("timeout"))
        return await wait(*args, **kwargs)

    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        board = backend.mcu
        sends = Sends(board.link)
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
        polled = [[name for message in messages
                   for name, _ in board.dictionary.decode(message)]
                  for sent_s, messages in sends.calls if sent_s >= since_s]
        polled = [names for names in polled if "get_clock" in names]
        assert polled and all(names[0] == "get_clock" and "queue_step" in names
                              for names in polled), polled
        await app.kernel.machine.wait_idle()


async def test_a_board_becoming_busy_is_polled_as_a_busy_one_riding_its_steps(
        mcu: VirtualMcu) -> None:
    """At rest the clock is polled once a second; a move begun just after a poll does not
    wait out that second: the first steps wake the watch, and its next poll rides one of the
    first blocks of steps, within a busy period of the last (a clock set back as the move began
    is read then, not a second later)."""
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        assert backend.mcu.poll_s == 1.0

        def polls() -> list[int]:
            return [clock for clock, name, _ in mcu.commands if name == "get_clock"]

        await asyncio.sleep(1.2)
        before = len(polls())
        for _ in range(150):  # just after an idle poll: the next idle one is a second away
            if len(polls()) > before:
                break
            await asyncio.sleep(0.01)
        last_idle = polls()[-1]
        await asyncio.sleep(0.1)
        await submit_all(app, ["G1 X50 F6000"])
        await asyncio.sleep(0.7)
        polled = [clock for clock in polls() if clock > last_idle]
        assert polled, "polled since the move began"
        after_s = (polled[0] - last_idle) / mcu.clock_hz
        assert after_s < mcu_module.BUSY_POLL_S + mcu_module.RIDE_S + 0.05, after_s
        steps = [clock for clock, name, _ in mcu.commands if name == "queue_step"]
        nearest_s = min(abs(clock - polled[0]) for clock in steps) / mcu.clock_hz
        assert nearest_s < 0.0005, "in a block of steps (read one after the other)"
        await app.kernel.machine.wait_idle()
