"""motiond's Grbl backend against real Grbl 1.1h (the grbl-sim rig: Grbl's own C, compiled for
this host) on a pseudo-terminal. What the board answers directly is the reference: every edge
case of ``edge-lines.txt`` gets the same reply through motiond's front; two clients stream in
turn without a phantom owner; a jog right after a command runs; hold, resume, a sender's Stop
(hold, then Ctrl-X) and the board's soft limits behave as on the board.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from server.app import App
from server.config_loader import build_config
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.runtime.grbl import GrblMachine
from server.transports.tcp import TcpTransport
from tests.support.grbl_rig import FAST_SETTINGS, GrblClient, grbl_direct, grbl_on_pty
from tests.support.helpers import running
from tests.support.rigs import rig
from tests.support.senders import CharCountingClient, wait_for

pytestmark = pytest.mark.usefixtures("quick_thread_switches")
# motiond's own answers, documented in the README: M999 unlocks (Smoothie), % marks a program.
DELIBERATE = {"M999": "ok", "%": "ok"}


def edge_lines() -> list[str]:
    lines = (rig("grbl-sim") / "edge-lines.txt").read_text().split("\n")
    return lines[:-1] if lines[-1] == "" else lines


@contextlib.asynccontextmanager
async def fronted(tmp_path: Path) -> AsyncIterator[App]:
    """motiond (grbl backend, TCP front) on a fresh Grbl board, its axes made fast."""
    async with grbl_on_pty(tmp_path) as device:
        config = build_config({
            "axes": {axis: {"steps_per_mm": 80, "max_rate_mm_s": 100, "accel_mm_s2": 500,
                            "max_mm": 300} for axis in "xyz"},
            "jobs": {"data_dir": str(tmp_path / "data")}, "tcp": {"port": 0},
            "backend": {"kind": "grbl", "serial": device, "status_hz": 20}}, "rig.toml")
        async with running(config, RealClock(), [TcpTransport]) as app:
            machine = app.kernel.machine
            assert isinstance(machine, GrblMachine)
            await wait_for(lambda: machine.controller.ready, 20.0, "the board's handshake")
            client = await connect(app)
            try:
                for setting in FAST_SETTINGS:
                    assert (await client.send(setting))[-1] == "ok"
            finally:
                client.close()
            yield app


async def connect(app: App) -> GrblClient:
    port: int = app.transports[0].port  # type: ignore[attr-defined]
    return await GrblClient.connect(port)


async def test_every_edge_line_gets_the_boards_own_reply_through_motiond(
        tmp_path: Path) -> None:
    lines = edge_lines()

    async def direct() -> tuple[list[tuple[str, ...]], int]:
        async with grbl_direct(tmp_path) as board:
            for setting in FAST_SETTINGS:
                await board.send(setting)
            return await board.each(lines), board.garbled

    async def through_motiond() -> tuple[list[tuple[str, ...]], int]:
        async with fronted(tmp_path) as app:
            client = await connect(app)
            try:
                return await client.each(lines), client.garbled
            finally:
                client.close()

    (reference, garbled_a), (ours, garbled_b) = await asyncio.gather(direct(), through_motiond())
    assert garbled_a + garbled_b <= 1, "the rig garbles a reply once in ~13,000 lines"
    differ = [(line, a[-1], b[-1]) for line, a, b in zip(lines, reference, ours, strict=True)
              if a[-1] != b[-1] and not a[-1].startswith("garbled:")
              and not b[-1].startswith("garbled:") and DELIBERATE.get(line) != b[-1]]
    assert differ == [], "line, the board's reply, motiond's"
    assert len(lines) >= 100


async def test_two_clients_stream_in_turn_and_a_jog_follows_any_command(tmp_path: Path) -> None:
    job = [f"G1 X{1 + n % 9} Y{n % 5} F20000" for n in range(60)]
    async with fronted(tmp_path) as app:
        port: int = app.transports[0].port  # type: ignore[attr-defined]
        first = await CharCountingClient.connect("127.0.0.1", port)
        second = await CharCountingClient.connect("127.0.0.1", port)
        try:
            assert (await first.command("$X"))[-1] == "ok"
            result = await second.stream(job)  # at once, no wait for a poll
            assert result.replies == ["ok"] * len(job)
            await wait_for(lambda: app.kernel.state is MachineState.IDLE, 20.0, "the job done")
            for command in ("G21", "$G", "M5"):
                assert (await first.command(command))[-1] == "ok"
                assert (await first.command("$J=G91 X-1 F5000"))[-1] == "ok", command
                await wait_for(lambda: not app.kernel.machine.busy, 10.0, "the jog done")
        finally:
            await first.close()
            await second.close()
        assert app.kernel.machine.stepgen.state.position_mm[0] == pytest.approx(
            1 + 59 % 9 - 3, abs=1e-3)


async def test_hold_resume_and_a_senders_stop_are_the_boards(tmp_path: Path) -> None:
    """bCNC's and LightBurn's Stop is ``!``, wait, Ctrl-X: no ALARM:3 once the hold is done,
    and the next lines run. ``!`` while idle is Hold:0, as on the board."""
    async with fronted(tmp_path) as app:
        client = await connect(app)
        try:
            assert (await client.send("G1 X-60 F3000"))[-1] == "ok"
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
            client.writer.write(b"!")
            await until_report(client, "<Hold:0|")
            client.writer.write(b"~")
            await until_report(client, "<Idle|")
        finally:
            client.close()


async def until_report(client: GrblClient, start: str, timeout_s: float = 10.0) -> str:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while not (report := await client.report()).startswith(start):
        assert loop.time() < deadline, f"{report}, never {start}"
        await asyncio.sleep(0.02)
    return report


async def test_soft_limits_are_the_boards_own_in_its_machine_space(tmp_path: Path) -> None:
    """With the board's soft limits off, motiond refuses no target; ``$22=1`` and ``$20=1``
    go to the board, and then its space is [-travel, 0] as Grbl's."""
    async with fronted(tmp_path) as app:
        client = await connect(app)
        try:
            assert (await client.send("G0 X-10 Y250"))[-1] == "ok", "the board has no limits"
            await client.settle()
            for setting in ("G0 X0 Y0", "$22=1", "$20=1"):
                assert (await client.send(setting))[-1] == "ok", setting
                await client.settle()
            axes = app.kernel.config.core.axes.values()
            assert [(a.min_mm, a.max_mm) for a in axes] == [(-200.0, 0.0)] * 3
            assert app.kernel.config.core.machine.soft_limits
            assert (await client.send("G0 X-150"))[-1] == "ok"
            await client.settle()
            client.writer.write(b"G0 X10\n")
            assert await client.line() == "ALARM:2", "Grbl's one reply to a soft-limit line"
            assert (await client.line()).startswith("[MSG:")
            client.writer.write(b"?")
            assert (await client.line()).startswith("<Alarm|"), "no error:N after it"
            assert app.kernel.alarm_code == 2
            unlocked = await client.send("$X")
            assert unlocked[-1] == "ok"
            assert unlocked.count("[MSG:Caution: Unlocked]") == 1, unlocked
        finally:
            client.close()
