"""Hold, resume, reset and M112 mean exactly the same from a TCP sender and the JSON API: one
implementation (server.kernel.control.MachineControl) behind every entry point."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running

JOB = b"G1 X300 F600\nG1 X0\n"


def port_of(app: App, name: str) -> int:
    return int(next(t.port for t in app.transports if t.name == name))  # type: ignore[attr-defined]


async def tcp_send(app: App, data: bytes) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port_of(app, "tcp"))
    await reader.readline()  # the banner
    writer.write(data)
    await writer.drain()
    await asyncio.sleep(0.2)
    writer.close()


async def api_call(app: App, method: str, **params: Any) -> Any:
    async with wsc.connect(f"ws://127.0.0.1:{port_of(app, 'http')}/api") as socket:
        await socket.send(json.dumps({"jsonrpc": "2.0", "id": 1, "method": method,
                                      "params": params}))
        while "id" not in (reply := json.loads(await asyncio.wait_for(socket.recv(), 5))):
            pass
    return reply["result"]


SENDERS = {
    "tcp": {"hold": lambda app: tcp_send(app, b"!"), "resume": lambda app: tcp_send(app, b"~"),
            "reset": lambda app: tcp_send(app, b"\x18"),
            "halt": lambda app: tcp_send(app, b"M112\n")},
    "api": {"hold": lambda app: api_call(app, "machine.hold"),
            "resume": lambda app: api_call(app, "machine.resume"),
            "reset": lambda app: api_call(app, "machine.reset"),
            "halt": lambda app: api_call(app, "gcode.send", lines="M112")},
}


async def playing(app: App) -> None:
    running_now = asyncio.Event()
    unsubscribe = app.kernel.events.subscribe(
        "state", lambda state: running_now.set() if state is MachineState.RUN else None)
    await app.kernel.jobs.save("long.nc", JOB)
    app.kernel.jobs.play("long.nc")
    await asyncio.wait_for(running_now.wait(), 5)
    unsubscribe()


@pytest.mark.parametrize("entry", list(SENDERS))
async def test_hold_pauses_the_job_and_resume_plays_it_on(entry: str, tmp_path: Path) -> None:
    config = make_config(jobs={"data_dir": str(tmp_path)})
    async with running(config, None, [TcpTransport, http_with_api]) as app:
        await playing(app)
        await SENDERS[entry]["hold"](app)
        await asyncio.sleep(0.5)
        progress = app.kernel.jobs.progress()
        assert progress is not None and progress.state == "paused"
        assert app.kernel.state is MachineState.HOLD
        assert app.kernel.machine.stepgen.state.speed_mm_s == 0.0
        await SENDERS[entry]["resume"](app)
        await asyncio.sleep(0.2)
        assert app.kernel.jobs.progress().state == "running"  # type: ignore[union-attr]
        assert app.kernel.machine.stepgen.state.speed_mm_s > 0.0


@pytest.mark.parametrize("entry", list(SENDERS))
async def test_reset_ends_the_job_with_alarm_3(entry: str, tmp_path: Path) -> None:
    config = make_config(jobs={"data_dir": str(tmp_path)})
    async with running(config, None, [TcpTransport, http_with_api]) as app:
        await playing(app)
        await SENDERS[entry]["reset"](app)
        await asyncio.sleep(0.3)
        assert app.kernel.jobs.progress().state == "aborted"  # type: ignore[union-attr]
        assert (app.kernel.state, app.kernel.alarm_code) == (MachineState.ALARM, 3)
        x_mm = app.kernel.machine.stepgen.state.position_mm[0]
        await asyncio.sleep(0.3)
        assert app.kernel.machine.stepgen.state.position_mm[0] == x_mm, "nothing runs on"


@pytest.mark.parametrize("entry", list(SENDERS))
async def test_m112_halts_with_alarm_40(entry: str, tmp_path: Path) -> None:
    config = make_config(jobs={"data_dir": str(tmp_path)})
    async with running(config, None, [TcpTransport, http_with_api]) as app:
        await playing(app)
        await SENDERS[entry]["halt"](app)
        await asyncio.sleep(0.3)
        assert (app.kernel.state, app.kernel.alarm_code) == (MachineState.ALARM, 40)
        assert not app.kernel.machine.stepgen.state.moving
