"""A read that carries several lines (character counting releases a few at once): each line
runs to its end in turn, most without a wait of their own, yet the stream keeps Grbl's rules:
one reply per line, in order, an error for the refused line only, and a realtime byte in the
middle of the read acting before the lines after it run.

A real App on the real clock (a hold lasts); sessions fed as a transport feeds them
(``Session.feed``)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import Event, MachineState
from server.sessions import session as session_module
from server.sessions.session import Session
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.senders import wait_for


@pytest.fixture
async def app() -> AsyncIterator[App]:
    async with running(make_config(), clock=RealClock()) as served:
        yield served


async def replies(session: Session, count: int) -> list[str]:
    """The next ``count`` reply lines (``ok``/``error:N``), pushes left out."""
    got: list[str] = []
    async with asyncio.timeout(10):
        while len(got) < count:
            chunk = await session.outbox.get()
            assert chunk is not None
            got += [line for line in chunk.decode().split("\r\n")
                    if line == "ok" or line.startswith("error:")]
    return got


async def started(app: App) -> Session:
    session = Session(app.kernel, "sender")
    session.start()
    assert await session.outbox.get()  # the banner
    return session


async def test_a_burst_of_lines_gets_one_reply_each_in_order_the_error_on_its_own_line(
        app: App) -> None:
    session = await started(app)
    try:
        await session.feed(b"G1 X1 F6000\nG1 X2\nG1 X3 Q\nG1 X4\nG5\nG1 Y5\n")
        got = await replies(session, 6)
        assert got == ["ok", "ok", "error:2", "ok", "error:20", "ok"], got
        await app.kernel.machine.wait_idle()
        assert app.kernel.machine.stepgen.state.position_mm[:2] == pytest.approx((4.0, 5.0))
    finally:
        await session.close()


async def test_a_hold_in_the_middle_of_a_burst_acts_before_the_lines_after_it_run(
        app: App) -> None:
    session = await started(app)
    planned_at_hold: list[int] = []
    planner = app.kernel.machine.planner
    app.kernel.events.subscribe(Event.HOLD,
                                lambda *args: planned_at_hold.append(planner.moves_appended))
    try:
        await session.feed(b"G1 X5 F600\n")
        assert await replies(session, 1) == ["ok"]
        await wait_for(lambda: app.kernel.state is MachineState.RUN, 5, "the move")
        before = planner.moves_appended
        await session.feed(b"G1 X5.1\nG1 X5.2\n!G1 X5.3\nG1 X5.4\n")
        assert planned_at_hold == [before]  # none of the read's lines had run yet
        assert app.kernel.state is MachineState.HOLD
        await session.feed(b"~")
        assert await replies(session, 4) == ["ok"] * 4
        assert planner.moves_appended == before + 4
        await app.kernel.machine.wait_idle()
        assert app.kernel.machine.stepgen.state.position_mm[0] == pytest.approx(5.4)
    finally:
        await session.close()


async def test_a_reset_in_the_middle_of_a_burst_drops_the_whole_read_unanswered(
        app: App) -> None:
    """MeerK40t's Stop: Ctrl-X, ``G1 S0``, ``M5`` in one write. Grbl flushes its receive
    buffer on the reset: the lines on both sides of it never run and get no reply; the
    banner follows, and the next read runs."""
    session = await started(app)
    try:
        await session.feed(b"G1 X1 F6000\nG1 X2\n\x18G1 Y3 F6000\nG1 Y4\n")
        assert b"Grbl" in await asyncio.wait_for(session.outbox.get(), 5)  # type: ignore[operator]
        await session.feed(b"G1 X5 F6000\n")
        got = await replies(session, 1)
        await app.kernel.machine.wait_idle()
        position = app.kernel.machine.stepgen.state.position_mm
    finally:
        await session.close()
    assert got == ["ok"]  # the next read's line alone
    assert position[:2] == pytest.approx((5.0, 0.0))


@pytest.mark.parametrize("stop", [b"M112", b"N7 m 0112", b" M 112 (halt)"])
async def test_an_m112_in_the_middle_of_a_burst_halts_before_the_lines_around_it_run(
        app: App, stop: bytes) -> None:
    """However it is spelled (the session looks for the code's digits before its pattern)."""
    session = await started(app)
    planner = app.kernel.machine.planner
    try:
        before = planner.moves_appended
        await session.feed(b"G1 X5 F600\nG1 X6\n" + stop + b"\nG1 X7\n")
        assert app.kernel.state is MachineState.ALARM
        assert planner.moves_appended == before  # none of the read's lines had run yet
    finally:
        await session.close()


@pytest.mark.parametrize("stop", [b"M410", b"m0410", b"N3 M 410"])
async def test_an_m410_in_the_middle_of_a_burst_stops_before_the_lines_after_it_run(
        app: App, stop: bytes) -> None:
    session = await started(app)
    planner = app.kernel.machine.planner
    try:
        await session.feed(b"G1 X5 F600\n")
        assert await replies(session, 1) == ["ok"]
        await wait_for(lambda: app.kernel.state is MachineState.RUN, 5, "the move")
        before = planner.moves_appended
        await session.feed(b"G1 X6\n" + stop + b"\nG1 Y7\n")
        assert planner.moves_appended == before
        assert app.kernel.machine.stepgen.idle  # the queued motion was dropped at once
        got = await replies(session, 3)
        assert got[0] == "error:45" and got[1:] == ["ok", "ok"], got
    finally:
        await session.close()


async def test_the_lines_of_a_read_are_answered_within_that_read_in_one_write(
        app: App, monkeypatch: pytest.MonkeyPatch) -> None:
    """The line path's cost per read (check-mode streaming at 0.33-0.39x a bare server): the
    lines of a read went to the executor task, their replies to the writer task, each a task
    switch and a loop turn. Lines that need no wait now run in the read that brought them,
    and their replies leave in one write, before ``feed`` returns. (The turn's time budget,
    0.3 ms, is lifted: a VM that stalls the first move's line past it hands the rest to the
    executor, as it should; that is not what this test is about.)"""
    monkeypatch.setattr(session_module, "YIELD_AFTER_S", 10.0)
    session = await started(app)
    written: list[bytes] = []
    session.outbox.write_now = lambda data: written.append(data) is None
    try:
        await asyncio.sleep(0.01)  # the executor waits for lines
        await session.feed(b"G1 X1 F6000\nG1 X2\nG1 X3 Q\nG1 X4\n")
        assert written == [b"ok\r\nok\r\nerror:2\r\nok\r\n"]
        await app.kernel.machine.wait_idle()
        assert app.kernel.machine.stepgen.state.position_mm[0] == pytest.approx(4.0)
    finally:
        await session.close()


async def test_a_long_read_s_replies_leave_as_its_lines_free_each_quarter_of_the_window(
        app: App, monkeypatch: pytest.MonkeyPatch) -> None:
    """A character-counting sender may refill as soon as a quarter of its 128-byte window
    is answered, while the rest of its read runs: 20 lines of 6 bytes leave their replies in
    four writes, one each time 6 lines (36 bytes) are answered, then the last 2."""
    monkeypatch.setattr(session_module, "YIELD_AFTER_S", 10.0)  # (as the test above)
    session = await started(app)
    written: list[bytes] = []
    session.outbox.write_now = lambda data: written.append(data) is None
    try:
        await asyncio.sleep(0.01)
        await session.feed(b"$C\n")
        await wait_for(lambda: app.kernel.status.state is MachineState.CHECK, 2.0, "check mode")
        written.clear()
        await session.feed(b"".join(b"G0 X%d\n" % (index % 10) for index in range(20)))
        assert written == [b"ok\r\n" * 6] * 3 + [b"ok\r\n" * 2]
    finally:
        await session.close()
