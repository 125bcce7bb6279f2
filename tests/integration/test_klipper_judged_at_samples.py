"""Fewer wake-ups (issue #41): while the owner samples, a block's retransmission timeout due
shortly before the owner's next sample is judged at that sample, not by a timer of its own (a
wake-up of the process per block sent, which only found the acknowledgement); a lost block is
still resent there, the deferral is bounded (``JUDGE_DEFER_MAX_S``), and a rest or a message
sent first (the emergency stop) judges on the timeout again. On the virtual MCU, over its
pty."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

import pytest

from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.link import JUDGE_DEFER_MAX_S, Link
from tests.support.klipper_machine import configured_link
from tests.support.virtual_mcu import VirtualMcu


class Timers:
    """Counts the retransmission timer's calls (each one a wake-up of the process)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.calls = 0
        original = Link._on_timer

        def counted(link: Link) -> None:
            self.calls += 1
            original(link)

        monkeypatch.setattr(Link, "_on_timer", counted)


@pytest.fixture
async def board() -> AsyncIterator[tuple[VirtualMcu, Link, Dictionary]]:
    """A configured virtual MCU and a link to it whose owner samples."""
    mcu = VirtualMcu(baud=250000).start()
    try:
        async with configured_link(mcu) as (link, encode):
            yield mcu, link, encode
    finally:
        mcu.stop()


def send_one(link: Link, encode: Dictionary) -> float:
    """One message in a block of its own, as a sample sends it; its timeout's deadline."""
    link.send(encode.encode("update_digital_out", oid=0, value=1))
    deadline_s = link.window.deadline_s()
    assert deadline_s is not None
    return deadline_s


async def sleep_until(when_s: float) -> None:
    await asyncio.sleep(max(0.0, when_s - time.monotonic()))


def updates(mcu: VirtualMcu) -> int:
    return sum(name == "update_digital_out" for _, name, _ in mcu.commands)


async def test_a_block_is_judged_at_the_next_sample_without_a_timer_wake_up(
        board: tuple[VirtualMcu, Link, Dictionary], monkeypatch: pytest.MonkeyPatch) -> None:
    mcu, link, encode = board
    timers = Timers(monkeypatch)
    deadline_s = send_one(link, encode)
    link.sample_due(deadline_s + 0.02)  # the owner's next sample, soon after the timeout
    await sleep_until(deadline_s + 0.015)
    link.sample()  # reads the acknowledgement: nothing to resend, the timer disarmed
    await asyncio.sleep(0.03)  # well past the deferred timer's time
    assert timers.calls == 0, "judged at the sample, not by a wake-up of its own"
    assert not link.window.inflight and link.window.retransmits == 0
    assert updates(mcu) == 1


async def test_a_lost_block_is_resent_by_the_sample_that_judges_it(
        board: tuple[VirtualMcu, Link, Dictionary], monkeypatch: pytest.MonkeyPatch) -> None:
    mcu, link, encode = board
    timers = Timers(monkeypatch)
    mcu.drop_blocks = 1
    deadline_s = send_one(link, encode)
    link.sample_due(deadline_s + 0.02)
    await sleep_until(deadline_s + 0.015)
    assert timers.calls == 0 and link.window.retransmits == 0, "the timer waits for the sample"
    link.sample()
    assert link.window.retransmits == 1, "the sample resent what its timeout had passed"
    for _ in range(100):
        await asyncio.sleep(0.01)
        link.sample()
        if not link.window.inflight:
            break
    assert not link.window.inflight and updates(mcu) == 1


@pytest.mark.parametrize("then", ["a sample due beyond the bound", "a rest"])
async def test_a_timeout_no_sample_comes_for_within_the_bound_is_judged_on_time(
        board: tuple[VirtualMcu, Link, Dictionary], monkeypatch: pytest.MonkeyPatch,
        then: str) -> None:
    mcu, link, encode = board
    timers = Timers(monkeypatch)
    mcu.drop_blocks = 1
    deadline_s = send_one(link, encode)
    if then == "a rest":
        link.sample_due(deadline_s + 0.04)
        link.rest()  # no sample comes after all (the ticks sleep)
    else:
        link.sample_due(deadline_s + JUDGE_DEFER_MAX_S + 0.05)
    await sleep_until(deadline_s + 0.02)
    assert timers.calls >= 1 and link.window.retransmits == 1, "resent on its timeout"


async def test_a_message_sent_first_is_judged_on_its_timeout(
        board: tuple[VirtualMcu, Link, Dictionary], monkeypatch: pytest.MonkeyPatch) -> None:
    mcu, link, encode = board
    timers = Timers(monkeypatch)
    # a sample announced, as while motion runs, within the bound after the block's timeout
    link.sample_due(time.monotonic() + link.window.rto_s + 0.03)
    mcu.drop_blocks = 1
    link.send_first(encode.encode("update_digital_out", oid=0, value=0))  # as emergency_stop
    deadline_s = link.window.deadline_s()
    assert deadline_s is not None
    link.sample_due(deadline_s + 0.03)  # the next tick's announcement changes nothing
    await sleep_until(deadline_s + 0.02)
    assert timers.calls >= 1 and link.window.retransmits == 1, "resent on its timeout"


async def test_a_resend_is_judged_on_its_timeout_so_two_losses_in_a_row_are_not_late(
        board: tuple[VirtualMcu, Link, Dictionary], monkeypatch: pytest.MonkeyPatch) -> None:
    """The first loss waits for the sample; its resend, lost too, is resent on its own
    timeout, not another deferral later (two deferrals made the steps it carried late: the
    firmware shut down, "Stepper too far in past")."""
    mcu, link, encode = board
    timers = Timers(monkeypatch)
    mcu.drop_blocks = 2  # the block and its first resend
    deadline_s = send_one(link, encode)
    link.sample_due(deadline_s + 0.02)
    await sleep_until(deadline_s + 0.015)
    link.sample()
    assert link.window.retransmits == 1 and link.window.recovering
    resend_deadline_s = link.window.deadline_s()
    assert resend_deadline_s is not None
    link.sample_due(resend_deadline_s + 0.03)  # the next sample, within the bound after it
    await sleep_until(resend_deadline_s + 0.02)
    assert timers.calls >= 1 and link.window.retransmits == 2, "resent on its own timeout"
    for _ in range(100):
        await asyncio.sleep(0.01)
        link.sample()
        if not link.window.inflight:
            break
    assert not link.window.inflight and not link.window.recovering and updates(mcu) == 1
