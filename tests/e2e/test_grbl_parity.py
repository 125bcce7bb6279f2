"""motiond's own machine (the simulated backend, Grbl dialect over TCP) beside real Grbl 1.1h
(the grbl-sim rig) on the same lines: a sender must not tell them apart. Both run at once on
the same axis settings; each test sends the same lines to both and compares what came back
(and, for ``G4``, when it came back).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import pytest

from server.app import App
from server.config_loader import build_config
from server.runtime.clock import RealClock
from server.transports.tcp import TcpTransport
from tests.support.grbl_rig import GrblClient, grbl_direct
from tests.support.helpers import running

pytestmark = pytest.mark.usefixtures("quick_thread_switches")
T = TypeVar("T")
STEPS_PER_MM, RATE_MM_MIN, ACCEL_MM_S2 = 250, 1200, 200
BOARD_SETTINGS = tuple(f"${base + axis}={value}" for base, value in
                       ((110, RATE_MM_MIN), (120, ACCEL_MM_S2)) for axis in range(3))


@contextlib.asynccontextmanager
async def motiond(tmp_path: Path, **machine: object) -> AsyncIterator[GrblClient]:
    """motiond on the simulated backend with the board's axes, and a Grbl client on TCP."""
    axis = {"steps_per_mm": STEPS_PER_MM, "max_rate_mm_s": RATE_MM_MIN / 60,
            "accel_mm_s2": ACCEL_MM_S2, "max_mm": 200}
    config = build_config({"axes": dict.fromkeys("xyz", axis), "tcp": {"port": 0},
                           "jobs": {"data_dir": str(tmp_path / "data")},
                           "protocol": {"dialect": "grbl"}, **machine}, "parity.toml")
    async with running(config, RealClock(), [TcpTransport]) as app:
        client = await _connect(app)
        try:
            yield client
        finally:
            client.close()


async def _connect(app: App) -> GrblClient:
    port: int = app.transports[0].port  # type: ignore[attr-defined]
    return await GrblClient.connect(port)


@contextlib.asynccontextmanager
async def board(tmp_path: Path) -> AsyncIterator[GrblClient]:
    """Real Grbl 1.1h, its axes set as motiond's."""
    async with grbl_direct(tmp_path) as client:
        for setting in BOARD_SETTINGS:
            assert (await client.send(setting))[-1] == "ok"
        yield client


async def side_by_side(tmp_path: Path, scenario: Callable[[GrblClient], Awaitable[T]],
                       **machine: object) -> tuple[T, T]:
    """The scenario on the board and on motiond at the same time: (board's, motiond's)."""
    async def on_board() -> T:
        async with board(tmp_path) as client:
            return await scenario(client)

    async def on_motiond() -> T:
        async with motiond(tmp_path, **machine) as client:
            return await scenario(client)

    return await asyncio.gather(on_board(), on_motiond())


async def test_g4_is_answered_when_the_move_before_it_and_the_dwell_have_run(
        tmp_path: Path) -> None:
    """CNCjs's ``%wait`` (``G4 P0.5``) and probing macros rely on it: ``ok`` for ``G4`` means
    the machine is done. 5 mm at 20 mm/s with 200 mm/s² takes 0.35 s, the dwell 0.2 s (short:
    the rig runs at about 0.97 x real time, a drift of 3 % of the run)."""
    async def dwell_after_move(client: GrblClient) -> tuple[list[str], str, float]:
        loop = asyncio.get_running_loop()
        assert await client.send("G1 X5 F1200") == ["ok"]
        start_s = loop.time()
        replies = await client.send("G4 P0.2")
        elapsed_s = loop.time() - start_s
        return replies, (await client.report()).split("|")[0], elapsed_s

    board_run, ours = await side_by_side(tmp_path, dwell_after_move)
    assert ours[:2] == board_run[:2] == (["ok"], "<Idle")
    assert board_run[2] > 0.5, "the board answered G4 after the move and the dwell"
    assert abs(ours[2] - board_run[2]) < 0.05, (ours[2], board_run[2])


async def after_reset(client: GrblClient, listen_s: float = 3.0) -> list[str]:
    """Ctrl-X, then the lines (status reports left out) up to Grbl's unlock message and those
    within 0.2 s after it, or all within ``listen_s``."""
    client.writer.write(b"\x18")
    lines: list[str] = []
    loop = asyncio.get_running_loop()
    deadline_s = loop.time() + listen_s
    with contextlib.suppress(TimeoutError):
        while True:
            async with asyncio.timeout_at(deadline_s):
                if not (line := await client.line()).startswith("<"):
                    lines.append(line)
            if line.endswith("to unlock]"):
                deadline_s = min(deadline_s, loop.time() + 0.2)
    return lines


async def until_moved(client: GrblClient, x_mm: float, timeout_s: float = 10.0) -> None:
    """Poll ``?`` until the machine runs past ``x_mm`` in X: the move is under way (the rig's
    Grbl reset on its first Run report raised no alarm, three times in three)."""
    loop = asyncio.get_running_loop()
    deadline_s = loop.time() + timeout_s
    while True:
        report = await client.report()
        x = float(report.partition("MPos:")[2].partition(",")[0] or "nan")
        if report.startswith("<Run") and x > x_mm:
            return
        assert loop.time() < deadline_s, f"the move never ran: {report}"
        await asyncio.sleep(0.01)


async def setting_numbers(client: GrblClient) -> list[str]:
    return [line.partition("=")[0] for line in await client.send("$$") if line != "ok"]


async def test_settings_list_and_homing_settings_are_grbls(tmp_path: Path) -> None:
    """``$$`` lists Grbl 1.1h's 34 settings; ``$23``-``$27`` take Grbl's values; ``$H`` with
    homing disabled (``$22=0``) is ``error:5``."""
    lines = ["$22=0", "$H", "$23=1", "$24=25", "$25=500", "$26=250", "$27=1", "$24=-1"]

    async def settings(client: GrblClient) -> tuple[list[str], list[list[str]]]:
        return await setting_numbers(client), [await client.send(line) for line in lines]

    board_run, ours = await side_by_side(tmp_path, settings)
    assert len(board_run[0]) == 34
    assert ours == board_run


async def test_a_reset_in_motion_is_alarm_3_the_banner_then_the_unlock_message(
        tmp_path: Path) -> None:
    async def reset_in_motion(client: GrblClient) -> list[str]:
        await client.send("G1 X10 F1200")
        await until_moved(client, 0.5)  # (a loaded rig starts late: a fixed wait missed)
        return (await after_reset(client))[:3]

    board_run, ours = await side_by_side(tmp_path, reset_in_motion)
    assert board_run == ["ALARM:3", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert ours == board_run


async def test_a_reset_during_homing_is_alarm_6_alone(tmp_path: Path) -> None:
    """Real Grbl seeks its switches (none ever closes on the rig) until the Ctrl-X. It also
    answers the cut ``$H`` with an ``ok`` right after the alarm (``mc_homing_cycle`` returns
    into ``$H``'s status); motiond drops the line's reply, as for any line a reset cut: that
    ``ok`` is left out of the comparison (a known difference, docs/senders.md)."""
    async def reset_while_homing(client: GrblClient) -> list[str]:
        assert await client.send("$22=1") == ["ok"]
        client.writer.write(b"$H\n")
        await asyncio.sleep(0.3)
        return [line for line in await after_reset(client) if not line.startswith("[MSG:")
                or "unlock" in line]

    homing = {"endstops": {"axes": {axis: {"direction": "max", "switch_at_mm": 150}
                                    for axis in "xyz"}}}
    board_run, ours = await side_by_side(tmp_path, reset_while_homing, **homing)
    assert board_run[1] == "ok"
    del board_run[1]
    assert board_run == ["ALARM:6", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert ours == board_run


async def test_build_info_buffer_and_position_reports_are_the_boards(tmp_path: Path) -> None:
    """``$I``'s block count and ``Bf:`` agree with Grbl's (15 free: the planner is empty), and
    ``MPos`` is on the step grid: X0.1234 at 250 steps/mm is 31 steps, 0.124 mm."""
    async def reports(client: GrblClient) -> tuple[str, str, str]:
        options = next(line for line in await client.send("$I") if line.startswith("[OPT:"))
        assert await client.send("$10=3") == ["ok"]  # MPos and Bf:
        await client.send("G1 X0.1234 F600")
        fields = (await client.settle()).strip("<>").split("|")
        buffer = next(field for field in fields if field.startswith("Bf:"))
        position = next(field for field in fields if field.startswith("MPos:"))
        return options.partition(",")[2], buffer, position

    board_run, ours = await side_by_side(tmp_path, reports)
    assert board_run == ("15,128]", "Bf:15,128", "MPos:0.124,0.000,0.000")
    assert ours == board_run
