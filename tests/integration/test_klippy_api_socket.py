"""[klippy_api] over its real Unix socket, with motiond in this process: owner-only socket,
emergency stop on arrival (ahead of a waiting script), bounded and strict framing, and
change-only subscription pushes."""

from __future__ import annotations

import asyncio
import json
import socket as sockets
import stat
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.klippy_client import KlippyClient


@asynccontextmanager
async def served(tmp_path: Path) -> AsyncIterator[tuple[App, Path]]:
    socket = tmp_path / "comms" / "klippy.sock"  # the folder is made
    config = make_config(klippy_api={"socket": str(socket)})
    async with running(config, RealClock()) as app:
        for _ in range(100):
            if socket.exists():
                break
            await asyncio.sleep(0.02)
        yield app, socket


@asynccontextmanager
async def client(socket: Path) -> AsyncIterator[KlippyClient]:
    reader, writer = await asyncio.open_unix_connection(str(socket))
    try:
        yield KlippyClient(reader, writer)
    finally:
        writer.close()


async def test_socket_is_owner_only_and_a_stale_one_is_replaced(tmp_path: Path) -> None:
    (tmp_path / "comms").mkdir()
    (tmp_path / "comms" / "klippy.sock").write_bytes(b"")  # not a socket: the machine alarms
    async with served(tmp_path) as (app, _):
        await asyncio.sleep(0.1)
        assert app.kernel.state is MachineState.ALARM
        assert "not a socket" in app.kernel.alarm_message
    (tmp_path / "comms" / "klippy.sock").unlink()
    with sockets.socket(sockets.AF_UNIX) as stale:  # left by a crash: nobody listens
        stale.bind(str(tmp_path / "comms" / "klippy.sock"))
    async with served(tmp_path) as (app, socket), client(socket) as api:
        assert stat.S_IMODE(socket.stat().st_mode) == 0o600
        assert (await api.call("info"))["result"]["state"] == "ready"
        assert app.kernel.state is MachineState.IDLE
    assert not socket.exists()  # removed at shutdown


async def test_emergency_stop_acts_while_a_script_waits(tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), client(socket) as api:
        moving = await api.send("gcode/script", script="G1 X90 F600")
        for _ in range(200):
            if app.kernel.machine.stepgen.state.speed_mm_s > 0:
                break
            await asyncio.sleep(0.01)
        assert (await api.call("emergency_stop")) == {"id": 2, "result": {}}
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 40
        assert (await api.answer(moving))["result"] == {}  # queued before the stop
        refused = await api.call("gcode/script", script="G1 X0")
        assert "locked out" in refused["error"]["message"]
        await asyncio.sleep(0.2)
        where = app.kernel.machine.stepgen.state.position_mm[0]
        assert 0 < where < 90
        status = await api.call("objects/query", objects={"webhooks": None})
        assert status["result"]["status"]["webhooks"]["state"] == "shutdown"


async def test_m112_in_a_script_queued_behind_another_acts_on_arrival(tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), client(socket) as api:
        await api.send("gcode/script", script="G1 X90 F300")
        await api.send("gcode/script", script="G4 P5")
        await asyncio.sleep(0.2)
        await api.send("gcode/script", script="M112")
        await asyncio.sleep(0.2)
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 40


async def test_broken_framing_closes_only_that_connection(tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket):
        async with client(socket) as bad:
            bad.writer.write(b"{not json}\x03")
            assert await asyncio.wait_for(bad.reader.read(), 5) == b""
        async with client(socket) as huge:
            huge.writer.write(b"{" + b" " * (1 << 20) + b" ")
            assert await asyncio.wait_for(huge.reader.read(), 5) == b""
        async with client(socket) as good:
            answer = await good.call("info")
            assert answer["result"]["state"] == "ready"
        assert app.kernel.state is MachineState.IDLE


async def test_subscription_pushes_only_what_changed(tmp_path: Path) -> None:
    async with served(tmp_path) as (_, socket), client(socket) as api:
        first = await api.call("objects/subscribe", objects={"toolhead": ["position"],
                                                             "print_stats": None},
                               response_template={"method": "process_status_update"})
        assert first["result"]["status"]["toolhead"]["position"] == [0.0, 0.0, 0.0, 0.0]
        await api.call("gcode/script", script="G1 X5 F3000")
        await asyncio.sleep(0.8)
        await api.call("info")  # collects what was pushed meanwhile
        pushes = [message for message in api.pushed
                  if message.get("method") == "process_status_update"]
        assert pushes, api.pushed
        assert all(set(push["params"]["status"]) == {"toolhead"} for push in pushes)
        assert pushes[-1]["params"]["status"]["toolhead"]["position"] == [5.0, 0.0, 0.0, 0.0]
        assert len({json.dumps(push["params"]["status"]) for push in pushes}) == len(pushes)


async def test_set_gcode_offset_shifts_the_work_offset_and_move_keeps_the_work_position(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), client(socket) as api:
        await api.call("gcode/script", script="G1 X5 Y5 F3000")
        answer = await api.call("gcode/script", script="SET_GCODE_OFFSET X_ADJUST=2")
        assert answer["result"] == {}
        status = (await api.call("objects/query", objects={"gcode_move": None}))["result"]
        moved = status["status"]["gcode_move"]
        assert moved["homing_origin"][0] == 2.0 and moved["position"][0] == 5.0
        assert moved["gcode_position"][0] == 3.0
        await api.call("gcode/script", script="SET_GCODE_OFFSET X=1 MOVE=1")
        await asyncio.sleep(0.5)
        status = (await api.call("objects/query", objects={"gcode_move": None}))["result"]
        moved = status["status"]["gcode_move"]
        assert moved["homing_origin"][0] == 1.0
        assert moved["position"][0] == 4.0 and moved["gcode_position"][0] == 3.0
        assert app.kernel.machine.stepgen.state.position_mm[0] == 4.0
