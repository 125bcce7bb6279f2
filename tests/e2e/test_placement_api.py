"""Placing, checking and framing a job over the JSON API: a real server on a real port, an
aiohttp WebSocket client, the real clock."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from server.runtime.clock import RealClock
from tests.support.api_client import api_config, serving

NEGATIVE_Y = "G21 G90\nG0 X0 Y0\nG1 X50 Y-20 F3000\nG1 X0 Y0\n"  # origin top-left, Y down
LONG = "G21 G90\nG1 X300 F600\n"


class Rpc:
    """JSON-RPC over one aiohttp WebSocket; notifications are skipped."""

    def __init__(self, socket: aiohttp.ClientWebSocketResponse) -> None:
        self.socket, self._ids = socket, itertools.count(1)

    async def request(self, method: str, **params: Any) -> dict[str, Any]:
        ident = next(self._ids)
        await self.socket.send_json({"jsonrpc": "2.0", "id": ident, "method": method,
                                     "params": params})
        async with asyncio.timeout(30):
            while True:
                message = await self.socket.receive_json()
                if message.get("id") == ident:
                    return dict(message)

    async def call(self, method: str, **params: Any) -> Any:
        reply = await self.request(method, **params)
        assert "error" not in reply, reply
        return reply["result"]

    async def error(self, method: str, **params: Any) -> dict[str, Any]:
        reply = await self.request(method, **params)
        assert "error" in reply, reply
        return dict(reply["error"])

    async def idle(self) -> dict[str, Any]:
        async with asyncio.timeout(20):
            while True:
                status = await self.call("machine.status")
                if status["state"] == "Idle" and not status["moving"]:
                    return dict(status)
                await asyncio.sleep(0.05)


@contextlib.asynccontextmanager
async def rpc_client(address: str, path: str = "/api") -> AsyncIterator[Rpc]:
    async with aiohttp.ClientSession() as session, \
            session.ws_connect(f"http://{address}{path}") as socket:
        yield Rpc(socket)


@contextlib.asynccontextmanager
async def machine(tmp_path: Path, **jobs: Any) -> AsyncIterator[tuple[Any, Rpc, str]]:
    config = api_config(tmp_path, jobs={"data_dir": str(tmp_path), **jobs})
    async with serving(config, RealClock()) as (app, address), rpc_client(address) as rpc:
        yield app, rpc, address


async def test_set_zero_go_to_zero_and_pick_a_coordinate_system(tmp_path: Path) -> None:
    async with machine(tmp_path) as (app, rpc, _):
        await rpc.call("gcode.send", lines=["G0 X100 Y50"])
        await rpc.idle()
        placed = await rpc.call("machine.set_zero", axes="XY")
        assert placed["wcs"] == "G54" and placed["wco_mm"] == {"X": 100.0, "Y": 50.0, "Z": 0.0}
        await rpc.call("gcode.send", lines=["G0 X20 Y30"])
        assert (await rpc.idle())["mpos"][:2] == [120.0, 80.0]
        await rpc.call("machine.go_to_zero")
        status = await rpc.idle()
        assert status["mpos"][:2] == [100.0, 50.0] and status["wpos"][:2] == [0.0, 0.0]
        assert (await rpc.call("machine.wcs", wcs="G55"))["wco_mm"]["X"] == 0.0
        await rpc.call("gcode.send", lines=["G0 X10"])
        await rpc.idle()
        assert (await rpc.call("machine.set_zero", axes="x"))["wco_mm"]["X"] == 10.0
        assert (await rpc.call("machine.wcs", wcs="G54"))["wco_mm"]["X"] == 100.0
        status = await rpc.call("machine.status")
        assert status["modal"]["wcs"] == "G54"


async def test_a_read_only_client_cannot_place_or_frame(tmp_path: Path) -> None:
    async with machine(tmp_path) as (app, rpc, address):
        await rpc.call("job.upload", name="neg.nc", text=NEGATIVE_Y)
        async with rpc_client(address, "/api?mode=observe") as observer:
            for method, params in (("machine.set_zero", {}), ("machine.go_to_zero", {}),
                                   ("machine.wcs", {"wcs": "G55"}),
                                   ("job.frame", {"name": "neg.nc"})):
                assert (await observer.error(method, **params))["code"] == 46, method
            assert not (await observer.call("job.place", name="neg.nc"))["fits"]
        assert app.kernel.machine.interpreter.wco() == (0.0, 0.0, 0.0)


async def test_a_job_that_does_not_fit_is_refused_and_fits_once_placed(tmp_path: Path) -> None:
    async with machine(tmp_path) as (app, rpc, _):
        await rpc.call("job.upload", name="neg.nc", text=NEGATIVE_Y)
        place = await rpc.call("job.place", name="neg.nc")
        assert not place["fits"] and place["size_mm"]["X"] == 50.0
        assert place["travel_mm"]["Y"] == [0.0, 300.0]
        refused = await rpc.error("job.start", name="neg.nc")
        assert refused["code"] == 47 and "Y: 20.000 mm below" in refused["message"]
        assert "Y work origin between 20.000 and 300.000" in refused["message"]
        assert (await rpc.call("machine.status"))["mpos"] == [0.0, 0.0, 0.0]
        await rpc.call("gcode.send", lines=["G0 X100 Y150"])
        await rpc.idle()
        await rpc.call("machine.set_zero", axes="XY")
        place = await rpc.call("job.place", name="neg.nc")
        assert place["fits"] and place["extent_min_mm"]["Y"] == 130.0
        job = await rpc.call("job.start", name="neg.nc")
        assert job["state"] == "running" and job["fit"]["fits"]


async def test_frame_traces_the_placed_extent_with_the_laser_off(tmp_path: Path) -> None:
    async with machine(tmp_path, frame_feed_mm_min=12000) as (app, rpc, _):
        await rpc.call("job.upload", name="neg.nc", text=NEGATIVE_Y)
        await rpc.call("gcode.send", lines=["G0 X100 Y150", "M3 S500"])  # laser armed
        await rpc.idle()
        await rpc.call("machine.set_zero", axes="XY")
        seen: list[tuple[float, float]] = []
        frame = asyncio.create_task(rpc.call("job.frame", name="neg.nc"))
        async with rpc_client(_) as watcher:
            while not frame.done() or (await watcher.call("machine.status"))["moving"]:
                status = await watcher.call("machine.status")
                assert status["power_pct"] == 0.0, "the laser stays off while framing"
                seen.append((status["mpos"][0], status["mpos"][1]))
                await asyncio.sleep(0.01)
        result = frame.result()
        assert result["lines"] == [f"$J=G53 G21 X{x} Y{y} F12000" for x, y in (
            ("100.000", "130.000"), ("150.000", "130.000"), ("150.000", "150.000"),
            ("100.000", "150.000"), ("100.000", "130.000"))]
        assert not result["stopped"]
        status = await rpc.idle()
        assert status["mpos"][:2] == [100.0, 130.0]
        assert max(x for x, _ in seen) == pytest.approx(150.0, abs=1.0), "it went round"
        assert all(129.99 <= y <= 150.01 for _, y in seen[len(seen) // 4:])


async def test_frame_is_refused_while_a_job_runs_and_a_hold_stops_it(tmp_path: Path) -> None:
    async with machine(tmp_path, frame_feed_mm_min=600) as (app, rpc, _):
        await rpc.call("job.upload", name="long.nc", text=LONG)
        await rpc.call("job.start", name="long.nc")
        assert (await rpc.error("job.frame", name="long.nc"))["code"] == 45
        await rpc.call("job.abort")
        await rpc.call("gcode.send", lines=["G0 X0"])
        await rpc.idle()
        frame = asyncio.create_task(rpc.call("job.frame", name="long.nc"))
        async with rpc_client(_) as other:
            await asyncio.sleep(1.0)
            await other.call("machine.hold")
            result = await frame
            status = await other.idle()
        assert 0.0 < status["mpos"][0] < 300.0, "stopped on the first side"
        await asyncio.sleep(0.5)
        assert (await rpc.call("machine.status"))["mpos"] == status["mpos"], "nothing more"
        assert len(result["lines"]) <= 5


async def test_a_hold_during_a_powered_frame_ends_it_and_the_call_says_so(tmp_path: Path) -> None:
    """With ``frame_power_s`` the frame is G1 moves at low power: a hold stops it, the laser
    goes off, and the call answers at once that it stopped and why (it waited as long as the
    hold lasted); nothing of the frame runs after it."""
    async with machine(tmp_path, frame_feed_mm_min=600, frame_power_s=10) as (app, rpc, address):
        await rpc.call("job.upload", name="box.nc", text="G21 G90\nG0 X5 Y5\nG1 X40 Y30 F3000\n")
        frame = asyncio.create_task(rpc.call("job.frame", name="box.nc"))
        async with rpc_client(address) as other:
            await asyncio.sleep(1.0)
            await other.call("machine.hold")
            async with asyncio.timeout(3):
                result = await frame
            status = await other.call("machine.status")
        assert result["stopped"] and result["reason"] == "hold", result
        assert status["power_pct"] == 0.0 and status["tool"]["mode"] == "M5", status
        await asyncio.sleep(0.5)
        assert (await rpc.call("machine.status"))["mpos"] == status["mpos"], "nothing more"
