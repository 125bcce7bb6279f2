"""Realtime bytes from a connection that may control: folded as Grbl's realtime flags, paced
when they flood, and never delaying another connection's first ``!``.

A real App on the real clock; sessions fed as a transport feeds them (``Session.feed``)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator

import pytest

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import Event, MachineState
from server.sessions.session import Session
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.senders import wait_for


@pytest.fixture
async def app() -> AsyncIterator[App]:
    async with running(make_config(), clock=RealClock()) as served:
        yield served


async def moving_session(app: App, name: str = "sender") -> Session:
    session = Session(app.kernel, name)
    session.start()
    await session.feed(b"G1 X200 F600\n")  # 20 s
    await wait_for(lambda: app.kernel.state is MachineState.RUN, 5, "the move")
    return session


@pytest.mark.slow
async def test_a_flood_of_holds_holds_once_and_a_resume_after_the_last_hold_resumes(
        app: App) -> None:
    holds: list[object] = []
    app.kernel.events.subscribe(Event.HOLD, lambda *args: holds.append(args))
    session = await moving_session(app)
    try:
        await session.feed(b"!" * 4095 + b"?")
        assert app.kernel.state is MachineState.HOLD and len(holds) == 1
        sent = b""
        while b"<" not in sent:
            sent += await asyncio.wait_for(session.outbox.get(), 1) or b""
        assert b"<Hold" in sent, "the report asked with the hold shows it"
        await session.feed(b"!" * 4096)
        assert len(holds) == 1, "a '!' while held changes nothing"
        await session.feed(b"~!~")
        assert app.kernel.state is MachineState.RUN, "the last of them was a resume"
        await session.feed(b"!~!" * 100)
        assert app.kernel.state is MachineState.HOLD, "the last of them was a hold"
    finally:
        await session.close()


async def test_override_steps_fold_into_one_change_each_clamped_as_alone(app: App) -> None:
    changes: list[object] = []
    app.kernel.events.subscribe("override", lambda *args: changes.append(args))
    session = await moving_session(app)
    machine = app.kernel.machine
    try:
        await session.feed(b"\x91" * 30)
        assert machine.feed_override == 200
        await session.feed(b"\x91" * 30)
        await session.feed(b"\x92\x92\x91\x9a")
        assert machine.feed_override == 190 and machine.spindle_override == 110
        await session.feed(b"\xa0\xa0\xa0")
        assert machine.tool.flood, "an odd number of toggles toggles"
    finally:
        await session.close()
    assert len(changes) <= 3, "one change per batch; the batch at the limit changed nothing"


async def test_a_reset_in_a_batch_drops_the_lines_before_it_and_those_right_behind_it(
        app: App) -> None:
    """As Grbl flushes its receive buffer on a reset: only the next read runs."""
    session = Session(app.kernel, "sender")
    session.start()
    try:
        await session.feed(b"\x91G1 X5 F600\n\x18G1 Y7 F600\n")
        await asyncio.sleep(0.1)
        assert app.kernel.machine.stepgen.idle, "nothing of that read moves"
        await session.feed(b"G1 Y2 F600\n")
        await wait_for(lambda: not app.kernel.machine.stepgen.idle, 5, "a move")
        await app.kernel.machine.wait_idle()
        position = app.kernel.machine.stepgen.state.position_mm
        override = app.kernel.machine.feed_override
    finally:
        await session.close()
    assert position[:2] == pytest.approx((0.0, 2.0)) and override == 100


async def test_the_operators_first_hold_acts_at_once_while_others_flood_the_total_budget(
        ) -> None:
    config = make_config(protocol={"realtime_total_bytes_per_s": 10.0})  # spent: seconds
    async with running(config, clock=RealClock()) as app:
        await operator_holds_amid_floods(app)


async def operator_holds_amid_floods(app: App) -> None:
    flooders = [Session(app.kernel, f"flood-{i}") for i in range(8)]
    operator = await moving_session(app, "operator")
    for flooder in flooders:
        flooder.start()
    floods = [asyncio.create_task(flooder.feed(b"\x91\x92" * 20_000)) for flooder in flooders]
    try:
        await wait_for(lambda: app.kernel.realtime_input.level(time.monotonic()) <= 0, 5,
                       "the flooders spent the total budget")
        started_s = time.monotonic()
        await operator.feed(b"!")
        took_s = time.monotonic() - started_s
        state = app.kernel.state
        assert not all(flood.done() for flood in floods), "the floods are paced, not done"
    finally:
        for flood in floods:
            flood.cancel()
        for session in (operator, *flooders):
            await session.close()
    assert state is MachineState.HOLD and took_s < 0.05
