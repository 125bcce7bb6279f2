"""motiond's Grbl backend against real Grbl 1.1h (the grbl-sim rig: Grbl's own C, compiled for
this host) on a pseudo-terminal. What the board answers directly is the reference: every edge
case of ``edge-lines.txt`` gets the same reply through motiond's front; two clients stream in
turn without a phantom owner; a jog right after a command runs; hold, resume, a sender's Stop
(hold, then Ctrl-X) and the board's soft limits behave as on the board.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager
from pathlib import Path

import pytest

from server.app import App
from server.backends.grbl.machine import GrblMachine
from server.config_loader import build_config
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.support.grbl_rig import FAST_SETTINGS, GrblClient, grbl_direct, grbl_on_pty
from tests.support.helpers import running
from tests.support.rigs import rig
from tests.support.senders import CharCountingClient, wait_for

pytestmark = pytest.mark.usefixtures("quick_thread_switches")
# motiond's own answers (docs/grbl-host.md): M999 unlocks (Smoothie), % marks a program.
DELIBERATE = {"M999": "ok", "%": "ok"}


def edge_lines() -> list[str]:
    lines = (rig("grbl-sim") / "edge-lines.txt").read_text().split("\n")
    return lines[:-1] if lines[-1] == "" else lines


# Lines motiond accepts or owns that the board refuses: its own M-codes mixed with a move (Grbl:
# error 20, and motiond runs nothing of the line), a line over Grbl's 80-character buffer once
# compacted (the board's error 11; motiond had read it: undone).
EXTRA_LINES = ["G1 X10 F100 M114", "G21 M400", "G0 X1 M115", "G20 G91 G0 X0." + "0" * 70 + "1",
               "G0 X0 Y0"]
_TOOL = re.compile(r" T\d+ ")


def same_modes(board: str, interpreter: str) -> bool:
    """``$G`` lines equal but for T: Grbl 1.1h sets T to 0 on every line without a T word
    (gcode.c, "only tracks value": ``gc_state.tool = gc_block.values.t``), motiond keeps the
    last one, as LinuxCNC; nothing depends on it on this backend."""
    return _TOOL.sub(" ", board) == _TOOL.sub(" ", interpreter)


@contextlib.asynccontextmanager
async def fronted(tmp_path: Path, axes: str = "xyz", *,
                  on_pty: Callable[[Path], AbstractAsyncContextManager[str]] = grbl_on_pty,
                  axis: dict[str, float] | None = None) -> AsyncIterator[App]:
    """motiond (grbl backend, TCP front) on a fresh board (Grbl's, or what ``on_pty``
    starts), its axes made fast (``axis``: each axis' config)."""
    axis = axis or {"steps_per_mm": 80, "max_rate_mm_s": 100, "accel_mm_s2": 500,
                    "max_mm": 300}
    async with on_pty(tmp_path) as device:
        config = build_config({
            "axes": {name: dict(axis) for name in axes},
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


async def modes(client: GrblClient) -> str:
    """The ``$G`` line, asked until two answers in a row agree (the rig's residue garbles a
    byte now and then on a loaded machine: ``F140`` for ``F100`` was seen)."""
    last = ""
    for _ in range(6):
        found = [text for text in await client.send("$G") if text.startswith("[GC:")]
        if found and found[0] == last:
            return last
        last = found[0] if found else ""
    raise AssertionError("no two $G answers alike in six")


async def replies_and_modes(client: GrblClient, lines: list[str],
                            machine: GrblMachine | None = None) -> list[tuple[str, str, str]]:
    """For each line, sent alone and settled: its reply, ``$G`` after it, and motiond's
    interpreter's own ``$G`` (through motiond)."""
    rows = []
    for text in lines:
        try:
            reply = (await client.send(text))[-1]
        except TimeoutError as exc:
            raise AssertionError(f"no reply to {text!r}: {client.pushed}") from exc
        await client.settle()
        ours = machine.interpreter.gc_report() if machine is not None else ""
        rows.append((reply, await modes(client), ours))
    return rows


async def test_every_edge_line_gets_the_boards_own_reply_and_leaves_the_same_modes(
        tmp_path: Path) -> None:
    """After each line the board's ``$G`` (direct), the front's ``$G`` and motiond's own
    interpreter agree: a line the board refuses changed nothing in motiond either."""
    lines = edge_lines() + ["G20 G1 F10", "$G", "G21 G0"] + EXTRA_LINES  # $G's F: mm/min

    async def direct() -> tuple[list[tuple[str, str, str]], int]:
        async with grbl_direct(tmp_path) as board:
            for setting in FAST_SETTINGS:
                await board.send(setting)
            return await replies_and_modes(board, lines), board.garbled

    async def through_motiond() -> tuple[list[tuple[str, str, str]], int, int]:
        async with fronted(tmp_path) as app:
            machine = app.kernel.machine
            assert isinstance(machine, GrblMachine)
            client = await connect(app)
            try:
                rows = await replies_and_modes(client, lines, machine)
                return rows, client.garbled, machine.lines_undone
            finally:
                client.close()

    (reference, garbled_a), (ours, garbled_b, undone) = await asyncio.gather(
        direct(), through_motiond())
    # The rig's residue: 2 in 25,781 lines idle, more on a loaded machine (1 + 1 seen in CI);
    # each side sends some 360 lines here. A garbled row is left out of the comparison below;
    # a few per side leave the comparison its bulk, a motiond that garbled would do it often.
    assert garbled_a <= 3 and garbled_b <= 3, "the rig garbles a reply now and then, not often"
    rows = list(zip(lines, reference, ours, strict=True))
    differ = [(line, a[0], b[0]) for line, a, b in rows
              if a[0] != b[0] and not a[0].startswith("garbled:")
              and not b[0].startswith("garbled:") and DELIBERATE.get(line) != b[0]]
    assert differ == [], "line, the board's reply, motiond's"
    assert [(line, a[1], b[1]) for line, a, b in rows if a[1] != b[1]] == [], "front $G"
    assert [(line, b[1], b[2]) for line, _, b in rows if not same_modes(b[1], b[2])] == [], \
        "line, the board's modes, motiond's interpreter's"
    assert [b[0] for _, _, b in rows[-len(EXTRA_LINES):-1]] == [
        "error:20", "error:23", "error:20", "error:11"]
    assert undone >= 1, "the long line was read by motiond, refused by the board, undone"
    assert len(lines) >= 100


async def test_dollar_commands_are_answered_by_the_board_line_for_line(tmp_path: Path) -> None:
    """``$$``, ``$#``, ``$G``, ``$I``, ``$N`` and writes to the board's settings and start-up
    lines, through motiond as direct; after Ctrl-X the board runs its start-up line (G20) and
    motiond reads the lines that follow in the board's modes."""
    before = ["$$", "$#", "$G", "$I", "$N", "$N0=G20", "$N", "$G", "$130=150", "$$", "$#"]
    after = ["$G", "G0 X1", "$N0=", "G21", "$N", "$G"]

    async def session(client: GrblClient) -> list[list[str]]:
        replies = [await client.send(text) for text in before]
        client.writer.write(b"\x18")
        await client.banner()
        await asyncio.sleep(0.3)  # the start-up line's own line (>G20:ok) before the next
        for line in after:
            replies.append(await client.send(line))
            await client.settle()
        pushed = [text for reply in replies for text in reply if ">G20:ok" in text]
        assert pushed in (["[MSG:controller: >G20:ok]"], [">G20:ok"]), "once, as a message"
        return [[text for text in reply if ">G20:ok" not in text
                 and not text.startswith("[MSG:controller error:")]  # told to every client
                for reply in replies]

    async def direct() -> list[list[str]]:
        async with grbl_direct(tmp_path) as board:
            for setting in FAST_SETTINGS:  # as fronted() writes them through motiond
                await board.send(setting)
            return await session(board)

    async def through_motiond() -> tuple[list[list[str]], dict[int, float], str, float]:
        async with fronted(tmp_path) as app:
            machine = app.kernel.machine
            assert isinstance(machine, GrblMachine)
            client = await connect(app)
            try:
                replies = await session(client)
                await client.settle()
                return (replies, machine.settings.values(), machine.interpreter.gc_report(),
                        machine.interpreter.position[0])
            finally:
                client.close()

    reference, (ours, settings, gc_after, x_mm) = await asyncio.gather(direct(),
                                                                      through_motiond())
    for line, a, b in zip(before + after, reference, ours, strict=True):
        if not any(text.startswith("garbled:") for text in a + b):  # the rig's residue
            assert a == b, (line, a, b)
    assert len(ours[0]) == 35 and ours[0][-2] == "$132=200.000", "all of the board's $$"
    assert ours[before.index("$N") + 2] == ["$N0=G20", "$N1=", "ok"]
    assert ours[len(before)][0].split()[3] == "G20", "the start-up line ran at the reset"
    assert settings[130] == 150.0, "motiond adopts the board's travel"
    assert x_mm == pytest.approx(25.4), "G0 X1 read in the board's G20"
    assert gc_after.split()[3] == "G21"


async def test_a_refused_line_is_undone_in_motiond_with_the_lines_streamed_after_it(
        tmp_path: Path) -> None:
    """Character counting: the board refuses the first line (too long for its buffer) after
    motiond read it in G20 G91 and read the next one in those modes; the board ran the next
    one in G21 G90, and so does motiond once the refusal arrives."""
    long_line = "G20 G91 G0 X0." + "0" * 70 + "1"
    async with fronted(tmp_path) as app:
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await connect(app)
        try:
            client.writer.write(f"{long_line}\nG0 X1\n".encode())
            replies = [await client.line() for _ in range(3)]
            assert [text for text in replies if not text.startswith("[MSG:")] == [
                "error:11", "ok"], replies
            report = await client.settle()
            assert report.startswith("<Idle|MPos:1.000,0.000,0.000"), report
            assert machine.interpreter.gc_report() == await modes(client)
            assert machine.interpreter.position == pytest.approx((1.0, 0.0, 0.0))
            assert machine.lines_undone == 1
        finally:
            client.close()


async def test_the_front_reports_the_boards_three_axes_with_two_configured(
        tmp_path: Path) -> None:
    async with fronted(tmp_path, axes="xy") as app:
        client = await connect(app)
        try:
            assert (await client.send("G0 X5 Y6"))[-1] == "ok"
            report = await client.settle()
            assert report.startswith("<Idle|MPos:5.000,6.000,0.000|"), report
            for _ in range(40):
                if "WCO:" in report:
                    break
                report = await client.report()
            assert "|WCO:0.000,0.000,0.000" in report, report
            offsets = await client.send("$#")
            assert offsets[0] == "[G54:0.000,0.000,0.000]"
        finally:
            client.close()


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
