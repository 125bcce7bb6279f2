"""A read-only connection runs nothing with an effect, whatever its first word (issue 17.1),
and while one source runs motion, others may query, hold and stop but not change state."""

from __future__ import annotations

import asyncio
import json

import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import VirtualClock
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running

TOKEN = "s3cret-token"
# Each starts with something a read-only connection may ask, then moves or fires the laser.
SMUGGLED = [
    "M114 G1 X150 Y100 F3000 M3 S1000",
    "M114 M3 S1000",
    "M119 G0 X20",
    "M105 G0 X20",
    "M114 F100",
    "M114 G92 X5",
    "M221 S500",
    "N5 M114 G0 X20",
]


def config() -> object:
    return make_config(protocol={"token": TOKEN, "unauthenticated": "read-only"},
                       http={"port": 0, "token": TOKEN}, laser={"pin": "laser"})


async def tcp_replies(port: int, lines: list[str]) -> list[str]:
    """Send ``lines`` over a fresh TCP connection; one reply (ok / error:N) per line."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write("".join(f"{line}\n" for line in lines).encode())
    replies: list[str] = []
    while len(replies) < len(lines):
        text = (await asyncio.wait_for(reader.readline(), 5)).decode().strip()
        if text == "ok" or text.startswith("error:"):
            replies.append(text)
    writer.close()
    return replies


def untouched(app: App) -> None:
    machine = app.kernel.machine
    assert machine.planner.position_mm == (0.0, 0.0, 0.0)
    assert machine.interpreter.position == (0.0, 0.0, 0.0)
    assert machine.interpreter.wco() == (0.0, 0.0, 0.0)
    assert machine.backend.output("laser") == 0.0
    assert machine.interpreter.modal_snapshot()["s"] == 0.0


async def test_a_read_only_tcp_connection_cannot_smuggle_a_move_behind_a_query() -> None:
    async with running(config(), VirtualClock(), [TcpTransport, http_with_api]) as app:
        port = app.transports[0].port  # type: ignore[attr-defined]
        replies = await tcp_replies(port, [*SMUGGLED, "M114", "$G"])
        assert replies == ["error:46"] * len(SMUGGLED) + ["ok", "ok"]
        untouched(app)


async def test_an_observer_websocket_cannot_smuggle_a_move_nor_log_in() -> None:
    async with running(make_config(http={"port": 0}), VirtualClock(), [http_with_api]) as app:
        port = app.transports[0].port  # type: ignore[attr-defined]
        async with wsc.connect(f"ws://127.0.0.1:{port}/ws?mode=observe") as socket:
            for line in [*SMUGGLED, "$AUTH=anything", "G0 X10"]:
                await socket.send(line + "\n")
            replies: list[str] = []
            while len(replies) < len(SMUGGLED) + 2:
                frame = str(await asyncio.wait_for(socket.recv(), 5))
                replies += [t for t in frame.split() if t == "ok" or t.startswith("error:")]
        assert replies[:len(SMUGGLED)] == ["error:46"] * len(SMUGGLED)
        assert replies[-1] == "error:46", "$AUTH must not turn an observer into a controller"
        untouched(app)


async def test_an_unauthenticated_api_connection_cannot_smuggle_a_move() -> None:
    async with running(config(), VirtualClock(), [http_with_api]) as app:
        port = app.transports[0].port  # type: ignore[attr-defined]
        async with wsc.connect(f"ws://127.0.0.1:{port}/api") as socket:
            await socket.send(json.dumps({"jsonrpc": "2.0", "id": 1, "method": "gcode.send",
                                          "params": {"lines": "\n".join(SMUGGLED)}}))
            while True:
                reply = json.loads(await asyncio.wait_for(socket.recv(), 5))
                if reply.get("id") == 1:
                    break
        results = reply["result"]["results"]
        assert [r["reply"] for r in results] == ["error:46"], "the first refusal stops the batch"
        untouched(app)


@pytest.mark.parametrize("line", ["G92 X0", "G91", "G20", "G0 X1", "$J=G91 X1 F100", "M106"])
async def test_a_second_connection_cannot_change_state_while_a_stream_runs(line: str) -> None:
    machine_config = make_config(switch={"fan": {"on_mcode": 106}})
    async with running(machine_config, None, [TcpTransport]) as app:
        port = app.transports[0].port  # type: ignore[attr-defined]
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"G1 X100 F600\n")
        while (await asyncio.wait_for(reader.readline(), 5)).strip() != b"ok":
            pass
        assert await tcp_replies(port, [line, "$G", "M114"]) == ["error:45", "ok", "ok"]
        writer.close()
        assert app.kernel.machine.interpreter.modal_snapshot()["distance"] == "absolute"
