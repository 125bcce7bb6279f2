"""A hostile or broken board (the scripted controller of test_grbl_fake_controller): noise on
the line, a board that stops answering, a chatty one, absurd reports. No client session is
dropped, the front's ``?`` stays quick, what is kept and logged stays bounded."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import pytest

from server.app import App
from server.backends.grbl.link import MAX_MESSAGES_PER_LINE
from server.backends.grbl.machine import GrblMachine
from server.runtime.events import MachineState
from tests.integration.test_grbl_fake_controller import client_of, linked
from tests.support.senders import CharCountingClient, wait_for

# The front's '?' while a board misbehaves. Goal: p99 <= 10 ms, as with a healthy board. The
# front's own work per '?' is ~0.03 ms (session._status, 2,000 calls, load 4.5); a round trip
# here is several turns of one event loop shared by motiond, the scripted board and the test's
# clients, on a 2-core machine shared with other runs. Seen at load 4-6: p99 0.7-15 ms in every
# case (1.5 MB/s of chatter included, once the board's bytes are read 1 kB per loop turn;
# before that, 30-100 ms), 0.6-18 ms with a healthy board; at load 8, up to 40 ms with a
# healthy board. So the bound is relative, and printed beside the goal: no worse than
# QUIET_FACTOR times the same poller with a healthy board measured just before, or than
# P99_FLOOR_S (a p99 of ~50 samples is their second-worst: one preemption of a loaded machine
# decides it), and never over P99_CEILING_S.
P99_GOAL_S = 0.010
P99_FLOOR_S = 0.025
QUIET_FACTOR = 5.0
P99_CEILING_S = 0.25
NOISY_STATE = b"<Run\x0b|MPos:0.000,0.000|FS:0,0>\r\n"
ABSURD = (b"<Idle|MPos:1e308,0|FS:0,0>\r\n<Idle|MPos:0,0|Ov:1000000000000,100,100>\r\n"
          b"<Idle|MPos:0,0|Bf:-1,99999999999>\r\n")


async def poll_round_trips(client: CharCountingClient, count: int) -> list[float]:
    """Seconds from ``?`` to the front's report, ``count`` times."""
    times = []
    for _ in range(count):
        started = time.perf_counter()
        client.writer.write(b"?")
        seen = []
        while not (line := await client._line(2.0)).startswith("<"):
            seen.append(line)  # pushed lines (a chatty board's, at most 20 a second)
            assert time.perf_counter() - started < 5.0, f"no report to '?': {seen[-5:]}"
        times.append(time.perf_counter() - started)
        await asyncio.sleep(0.02)
    return times


def p99(times: list[float]) -> float:
    ordered = sorted(times)
    return ordered[max(0, int(len(ordered) * 0.99) - 1)]


@contextlib.asynccontextmanager
async def front_polled(app: App, case: str, company: Callable[[], Awaitable[object]] | None = None
                       ) -> AsyncIterator[list[float]]:
    """A sender polling the front's ``?`` every 20 ms while the block runs (its round trips,
    seconds); then the goal: p99 within ``QUIET_FACTOR`` times what the same poller sees with
    a healthy board on this machine now (beside ``company()``, the case's other clients), and
    at most ``P99_CEILING_S``."""
    quiet = await client_of(app)
    try:
        baseline, *_ = await asyncio.gather(
            poll_round_trips(quiet, 25), *([company()] if company is not None else []))
    finally:
        await quiet.close()
    client = await client_of(app)
    times: list[float] = []
    done = asyncio.Event()

    async def poll() -> None:
        while not done.is_set():
            times.extend(await poll_round_trips(client, 1))

    task = asyncio.create_task(poll())
    try:
        yield times
    finally:
        done.set()  # (not cancel: Python 3.11's wait_for can swallow it, and the poller runs on)
        await asyncio.wait_for(task, 10.0)
        await client.close()
    worst_s, calm_s = p99(times), p99(baseline)
    print(f"front '?' p99 with {case}: {worst_s * 1e3:.1f} ms (n={len(times)}, max "
          f"{max(times) * 1e3:.1f} ms; goal {P99_GOAL_S * 1e3:.0f} ms); healthy board just "
          f"before: {calm_s * 1e3:.1f} ms")
    assert len(times) >= 10, "the poller kept its session"
    assert worst_s <= max(P99_FLOOR_S, QUIET_FACTOR * calm_s), case
    assert worst_s <= P99_CEILING_S, case


async def test_noise_in_reports_breaks_no_session_and_the_front_answers_quickly(
        tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        clients = [await client_of(app) for _ in range(10)]
        try:
            async with front_polled(app, "noise in every report, 10 more pollers", lambda:
                                    asyncio.gather(*(poll_round_trips(c, 25) for c in clients))):
                fake.noise = (NOISY_STATE + ABSURD + os.urandom(4096).replace(b"\n", b" ")
                              + b"\r\n")
                await asyncio.gather(*(poll_round_trips(c, 30) for c in clients))
            assert app.kernel.state is MachineState.IDLE, "the good reports between still count"
            for client in clients:
                assert (await client.command("$G"))[-1] == "ok", "every session still there"
        finally:
            for client in clients:
                await client.close()
        assert machine.controller.link.garbled_reports >= 30
        status = machine.controller.status
        assert status is not None and status.machine_mm == (0.0, 0.0), "nothing absurd adopted"
        assert machine.controller.link.buffer_bytes == 255


@pytest.mark.slow
async def test_a_board_that_stops_answering_alarms_turns_tools_off_and_is_reconnected(
        tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await client_of(app)
        try:
            fake.report = b"<Run|MPos:1.000,0.000|FS:600,0>\r\n"
            await wait_for(lambda: app.kernel.state is MachineState.RUN, 2.0, "Run")
            resets = fake.resets
            async with front_polled(app, "a board gone silent"):
                fake.polls_answered = False  # hung: a stale <Run...> is the last it said
                started = time.monotonic()
                await wait_for(lambda: app.kernel.alarm_code == 42, 4.0, "ALARM:42")
                silent_s = time.monotonic() - started
            assert 1.8 < silent_s < 3.5, f"alarmed after {silent_s:.2f} s (default 2 s)"
            assert "not answering" in app.kernel.alarm_message
            assert fake.resets > resets, "Ctrl-X: the board's tools off if it still listens"
            fake.polls_answered, fake.report = True, b"<Idle|MPos:1.000,0.000|FS:0,0>\r\n"
            await wait_for(lambda: fake.connections == 2 and machine.controller.ready, 5.0,
                           "the reconnection")
            assert (await client.command("$X"))[-1] == "ok"
            assert (await client.command("G0 X2"))[-1] == "ok"
        finally:
            await client.close()


async def test_lines_printed_while_a_line_is_in_flight_are_bounded(tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            fake.holding = True
            client.writer.write(b"G0 X5\n")
            await wait_for(lambda: fake.lines[-1:] == ["G0X5"], 2.0, "the line at the board")
            async with front_polled(app, "60,000 lines printed for a line in flight"):
                fake.noise = b"".join(b"[MSG:chatter %d]\r\n" % n for n in range(3000))
                await asyncio.sleep(1.0)  # about 20 polls: 60,000 lines printed for one line
                fake.noise = b""
            fake.release()
            reply = []
            while (line := await client._line(5.0)) != "ok":
                reply.append(line)
        finally:
            await client.close()
        kept = [line for line in reply if "chatter" in line]
        assert len(kept) == MAX_MESSAGES_PER_LINE
        assert "more lines from the controller" in reply[-1]


@pytest.mark.slow
async def test_a_chatty_board_neither_disconnects_clients_nor_floods_them_or_the_log(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    async with linked(tmp_path) as (fake, app):
        reader, sleeper = await client_of(app), await client_of(app)  # one reads, one not
        try:
            caplog.set_level(logging.INFO)
            caplog.clear()
            pushed: list[str] = []
            async with front_polled(app, "a chatty board (1.5 MB/s)"):
                fake.noise = b"".join(b"[MSG:chatter %d]\r\n" % n for n in range(4000))
                fake.noise += os.urandom(20_000).replace(b"\n", b" ") + b"\r\n"
                deadline = time.monotonic() + 2.0
                while time.monotonic() < deadline:
                    try:
                        pushed.append(await reader._line(deadline - time.monotonic() + 0.5))
                    except TimeoutError:
                        break
                window = len(pushed)
                while not any("more lines not shown" in line for line in pushed):
                    pushed.append(await reader._line(5.0))  # the summary, at the latest here
                fake.noise = b""
            assert (await reader.command("$G"))[-1] == "ok"
            assert (await sleeper.command("$G"))[-1] == "ok", "the slow reader is still here"
        finally:
            await reader.close()
            await sleeper.close()
        chatter = [line for line in pushed[:window] if line.startswith("[MSG:")]
        assert 10 <= len(chatter) <= 40 + 2 * 2 * 20, "a burst, then 20 lines a second"
        warnings = [r for r in caplog.records if r.levelno >= logging.WARNING and (
            r.name == "motiond.grbl" or "not safe" in r.getMessage()
            or "not reading" in r.getMessage())]  # not a loop-stall note of a loaded machine
        assert len(warnings) <= 3, [r.getMessage()[:80] for r in warnings]


async def test_a_noisy_bf_never_grows_the_send_window(tmp_path: Path) -> None:
    """The first report says 896 free bytes (noise); the buffer is adopted only once two
    reports in a row agree, and a later figure never grows it."""
    noisy = b"<Idle|MPos:0.000,0.000|Bf:15,896|FS:0,0>\r\n"
    async with linked(tmp_path, reports=(noisy,)) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        await wait_for(lambda: machine.controller.link.buffer_bytes == 255, 2.0, "Bf: 255")
        async with front_polled(app, "a noisy Bf: in every report"):
            fake.report = noisy
            await asyncio.sleep(0.5)
        assert machine.controller.link.buffer_bytes == 255
