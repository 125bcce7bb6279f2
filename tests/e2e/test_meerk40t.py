"""MeerK40t (PyPI, console mode) as the sender: it connects to ``ws://host:port/`` (the root,
where FluidNC and the ESP32 WebUIs serve their socket), which motiond once answered with the
web page, and MeerK40t exited with a traceback. Now it moves the machine, and its Stop (Ctrl-X)
stops a move midway as on Grbl."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.meerk40t import meerk40t
from tests.support.senders import wait_for


@pytest.fixture
async def app() -> AsyncIterator[App]:
    async with running(make_config(), RealClock(), [http_with_api]) as served:
        yield served


def position(app: App) -> tuple[float, ...]:
    return tuple(app.kernel.machine.stepgen.state.position_mm)


async def test_meerk40t_on_the_root_websocket_moves_and_stops_the_machine(
        app: App, tmp_path: Path) -> None:
    port: int = app.transports[0].port  # type: ignore[attr-defined]
    async with meerk40t(tmp_path) as program:
        await program.grbl_device_on("127.0.0.1", port)
        await program.command("grbl G0 X5 Y3")
        await wait_for(lambda: position(app)[:2] == (5.0, 3.0), 20.0, "MeerK40t's move")
        await program.command("grbl G1 X200 F1200")  # 10 s
        await wait_for(lambda: position(app)[0] > 10.0, 10.0, "the long move under way")
        await program.command("estop")  # MeerK40t's Stop: Ctrl-X
        await wait_for(lambda: not app.kernel.machine.busy, 5.0, "the stop")
        stopped_x = position(app)[0]
        alarm = app.kernel.alarm_code
        await asyncio.sleep(0.5)
        await program.command("clear_alarm")  # $X
        await wait_for(lambda: app.kernel.state is MachineState.IDLE, 5.0, "$X")
        output = program.output
    assert 10.0 < stopped_x < 150.0 and position(app)[0] == stopped_x
    assert alarm == 3, "a reset in motion is Grbl's ALARM:3"
    assert "Traceback" not in output, output[-3000:]
