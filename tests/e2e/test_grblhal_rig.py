"""motiond's Grbl backend hosting real grblHAL (the grblhal-sim rig: grblHAL's core compiled for
this host) on a pseudo-terminal, beside the same board driven directly: what the board answers
directly is the reference. grblHAL makes an error sticky (every later G-code line gets it until
an empty line): through motiond a refused line must not take the lines behind it down. The
same job, hold and resume, Stop, soft limits and error cases as tests/e2e/test_grbl_rig.py.
(A Ctrl-X in mid-motion is not here: the simulated grblHAL then now and then prints no
banner and answers nothing more, 1 run in 3 to 6 here; motiond alarms and reconnects it, as a
silent board must be, but the run cannot go on. Stop, a Ctrl-X once held, is.)
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from server.app import App
from server.backends.grbl.machine import GrblMachine
from server.runtime.events import MachineState
from tests.e2e.test_grbl_rig import connect, until_report
from tests.e2e.test_grbl_rig import fronted as grbl_fronted
from tests.support.grbl_rig import FAST_SETTINGS, GrblClient
from tests.support.grblhal_rig import grblhal_direct, grblhal_on_pty
from tests.support.senders import CharCountingClient, wait_for

pytestmark = pytest.mark.usefixtures("quick_thread_switches")


def fronted(tmp_path: Path) -> contextlib.AbstractAsyncContextManager[App]:
    """motiond (grbl backend, TCP front) on a fresh grblHAL board, its axes made fast."""
    return grbl_fronted(tmp_path, on_pty=grblhal_on_pty, axis={
        "steps_per_mm": 250, "max_rate_mm_s": 300, "accel_mm_s2": 2000, "max_mm": 200})


@contextlib.asynccontextmanager
async def board(tmp_path: Path) -> AsyncIterator[GrblClient]:
    async with grblhal_direct(tmp_path) as client:
        for setting in FAST_SETTINGS:
            assert (await client.send(setting))[-1] == "ok"
        yield client


async def each_alone(client: GrblClient, lines: list[str]) -> list[str]:
    """The board's own reply to each line, sent alone; after an error an empty line clears
    grblHAL's sticky error (its ``ok`` left out), so each line is judged on its own."""
    replies = []
    for text in lines:
        reply = (await client.send(text))[-1]
        if reply.startswith("error:"):
            assert await client.send("") == ["ok"]
        replies.append(reply)
        await client.settle()
    return replies


async def test_motiond_recognises_grblhal_and_relays_its_own_reports(tmp_path: Path) -> None:
    """``$I`` (with ``[FIRMWARE:grblHAL]``, ``[AXS:…]``, ``[NEWOPT:…]``) and ``$$`` (its 83
    settings) through motiond as from the board."""
    async def direct() -> list[list[str]]:
        async with board(tmp_path) as client:
            return [await client.send("$I"), await client.send("$$")]

    async def through_motiond() -> tuple[list[list[str]], bool]:
        async with fronted(tmp_path) as app:
            machine = app.kernel.machine
            assert isinstance(machine, GrblMachine)
            client = await connect(app)
            try:
                replies = [await client.send("$I"), await client.send("$$")]
            finally:
                client.close()
            handshake = machine.controller.handshake
            return replies, handshake is not None and handshake.grblhal

    reference, (ours, recognised) = await asyncio.gather(direct(), through_motiond())
    assert recognised and "[FIRMWARE:grblHAL]" in ours[0]
    assert any(line.startswith("[AXS:") for line in ours[0])
    assert [line for line in ours[0] if not line.startswith("[OPT:")] == [
        line for line in reference[0] if not line.startswith("[OPT:")]
    assert len(ours[1]) - 1 == len(reference[1]) - 1 >= 80
    assert ours[1] == reference[1]


async def test_a_refused_line_does_not_poison_the_lines_streamed_behind_it(
        tmp_path: Path) -> None:
    """``$99=1`` is the board's to refuse (grblHAL: ``error:53``), and grblHAL would then
    refuse every G-code line behind it with the same error: through motiond, streamed in one
    write, each line gets the board's own answer (53 as Grbl's 20) and the moves run."""
    lines = ["$99=1", "G0 X5", "G1 X10 F6000", "$abc", "G0 Y3", "G0 X12"]

    async def direct() -> list[str]:
        async with board(tmp_path) as client:
            return await each_alone(client, lines)

    async def through_motiond() -> tuple[list[str], str]:
        async with fronted(tmp_path) as app:
            port: int = app.transports[0].port  # type: ignore[attr-defined]
            sender = await CharCountingClient.connect("127.0.0.1", port)
            try:
                result = await sender.stream(lines)
            finally:
                await sender.close()
            client = await connect(app)
            try:
                return result.replies, await client.settle()
            finally:
                client.close()

    reference, (ours, report) = await asyncio.gather(direct(), through_motiond())
    assert reference == ["error:53", "ok", "ok", "error:3", "ok", "ok"]
    assert ours[1:3] == ours[4:] == ["ok", "ok"], ours
    # 53 is beyond Grbl 1.1h's table (server/errors.py): senders get 20, the board's number
    # is in the [MSG:controller error: ...] every client is told
    # and motiond refuses $abc itself, with Grbl 1.1h's number (grblHAL's is 3)
    assert ours[0] == "error:20" and ours[3] == "error:2"
    assert report.startswith("<Idle|MPos:12.000,3.000,0.000"), report


async def test_a_job_streamed_through_motiond_ends_where_the_board_does(tmp_path: Path) -> None:
    job = [f"G1 X{1 + n % 9} Y{n % 5} F20000" for n in range(60)] + ["G0 X7.2 Y1.5"]
    async with fronted(tmp_path) as app:
        port: int = app.transports[0].port  # type: ignore[attr-defined]
        sender = await CharCountingClient.connect("127.0.0.1", port)
        try:
            result = await sender.stream(job)
        finally:
            await sender.close()
        await wait_for(lambda: app.kernel.state is MachineState.IDLE, 20.0, "the job done")
        client = await connect(app)
        try:
            report = await client.settle()
        finally:
            client.close()
    assert result.replies == ["ok"] * len(job)
    assert report.startswith("<Idle|MPos:7.200,1.500,0.000"), report


async def test_hold_resume_a_senders_stop_and_a_tool_change_are_the_boards(
        tmp_path: Path) -> None:
    """``!`` ``~`` as on the board; Stop (``!``, then Ctrl-X once held) leaves it Idle; grblHAL's
    ``M6`` holds it in ``Tool`` until a cycle start."""
    async with fronted(tmp_path) as app:
        client = await connect(app)
        try:
            assert (await client.send("G1 X150 F1500"))[-1] == "ok"  # 6 s: time to spare
            client.writer.write(b"!")
            await until_report(client, "<Hold:0|")
            client.writer.write(b"~")
            await until_report(client, "<Run|")
            client.writer.write(b"!")
            await until_report(client, "<Hold:0|")
            client.writer.write(b"\x18")
            await client.banner()
            assert (await client.settle()).startswith("<Idle|"), "no alarm after a done hold"
            assert app.kernel.alarm_code == 0
            assert (await client.send("G0 X0"))[-1] == "ok"
            await client.settle()
            assert (await client.send("M6 T1"))[-1] == "ok"
            await until_report(client, "<Tool|")
            held = app.kernel.state
            client.writer.write(b"~")
            await until_report(client, "<Idle|")
            assert (await client.send("G0 X2"))[-1] == "ok", "the lines after it run"
            assert (await client.settle()).startswith("<Idle|MPos:2.000,")
        finally:
            client.close()
    assert held is MachineState.HOLD


async def test_soft_limits_and_errors_are_the_boards(tmp_path: Path) -> None:
    """Homing and soft limits set through motiond go to the board; a target beyond them is
    ALARM:2 alone, as on Grbl; lines refused by motiond's reading carry Grbl's numbers."""
    async with fronted(tmp_path) as app:
        client = await connect(app)
        try:
            for setting in ("$22=1", "$20=1"):
                assert (await client.send(setting))[-1] == "ok", setting
            axes = app.kernel.config.core.axes.values()
            assert [(a.min_mm, a.max_mm) for a in axes] == [(-200.0, 0.0)] * 3
            assert (await client.send("G0 X-150"))[-1] == "ok"
            await client.settle()
            assert [(await client.send(line))[-1] for line in ("G1 X-", "G0 G1 X1")] == [
                "error:2", "error:24"]
            assert (await client.send("G0 X-100"))[-1] == "ok", "not poisoned"
            await client.settle()
            client.writer.write(b"G0 X10\n")
            assert await client.line() == "ALARM:2", "Grbl's one reply to a soft-limit line"
            assert app.kernel.alarm_code == 2
            assert (await client.send("$X"))[-1] == "ok"
            assert (await client.send("G0 X-20"))[-1] == "ok"
            assert (await client.settle()).startswith("<Idle|MPos:-20.000,")
        finally:
            client.close()
