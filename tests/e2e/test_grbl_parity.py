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
    the machine is done. 10 mm at 20 mm/s with 200 mm/s² takes 0.6 s, the dwell 0.3 s."""
    async def dwell_after_move(client: GrblClient) -> tuple[list[str], str, float]:
        loop = asyncio.get_running_loop()
        assert await client.send("G1 X10 F1200") == ["ok"]
        start_s = loop.time()
        replies = await client.send("G4 P0.3")
        elapsed_s = loop.time() - start_s
        return replies, (await client.report()).split("|")[0], elapsed_s

    board_run, ours = await side_by_side(tmp_path, dwell_after_move)
    assert ours[:2] == board_run[:2] == (["ok"], "<Idle")
    assert board_run[2] > 0.8, "the board answered G4 after the move and the dwell"
    assert abs(ours[2] - board_run[2]) < 0.05, (ours[2], board_run[2])
