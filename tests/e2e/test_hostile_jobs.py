"""Jobs never take the machine from someone else, and never hold a whole file in memory.

A job starts only when the machine is idle and nobody else is using it: ``job.start`` on the
JSON API, ``play`` on TCP and on /ws (and MQTT's ``cmd/job``, which calls the same
:meth:`Jobs.play`) all answer 45 while a sender's stream runs, and the sender's lines all run.
Real sockets and real WebSocket clients (aiohttp's) against a server in this process.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import aiohttp

from server.api.server import http_with_api
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.e2e.test_hostile_lines import Tcp, http_port, tcp_port
from tests.support.helpers import running

JOB = "G90\nG0 X0 Y0\nG0 X5\n"


async def rpc(socket: aiohttp.ClientWebSocketResponse, method: str, **params: Any) -> Any:
    """One JSON-RPC request on /api; its response (notifications skipped)."""
    await socket.send_str(json.dumps({"jsonrpc": "2.0", "id": 1, "method": method,
                                      "params": params}))
    async with asyncio.timeout(10):
        while True:
            message = json.loads((await socket.receive()).data)
            if message.get("id") == 1:
                return message


async def ws_reply(socket: aiohttp.ClientWebSocketResponse, line: str) -> str:
    """The reply to one /ws line (pushed lines skipped)."""
    await socket.send_str(line)
    async with asyncio.timeout(10):
        while True:
            text = str((await socket.receive()).data).strip()
            if text == "ok" or text.startswith("error:"):
                return text


async def test_no_path_starts_a_job_while_a_sender_streams_and_its_lines_all_run() -> None:
    config = make_config(axes={"x": {"steps_per_mm": 80, "max_rate_mm_s": 500,
                                     "accel_mm_s2": 3000, "max_mm": 1000}})
    async with running(config, clock=RealClock(),
                       transports=[TcpTransport, http_with_api]) as app:
        (Path(config.core.jobs.data_dir) / "cut.nc").write_text(JOB)
        sender, other = await Tcp.open(tcp_port(app)), await Tcp.open(tcp_port(app))
        moves = 20
        await sender.send(b"G91\n" + b"G1 X1 F600\n" * moves)  # 2 s of motion
        await sender.received.until(lambda got: got.count("ok") >= 3)
        assert app.kernel.state is MachineState.RUN
        async with aiohttp.ClientSession() as http:
            base = f"http://127.0.0.1:{http_port(app)}"
            api = await http.ws_connect(f"{base}/api")
            line_socket = await http.ws_connect(f"{base}/ws")
            refused_api = await rpc(api, "job.start", name="cut.nc")
            refused_ws = await ws_reply(line_socket, "play cut.nc")
            await other.send(b"play cut.nc\n")
            await other.received.until(lambda got: any(x.startswith("error:") for x in got))
            assert app.kernel.jobs.progress() is None, "no job started"
            await sender.received.until(lambda got: got.count("ok") == moves + 1, 10)
            async with asyncio.timeout(10):
                await app.kernel.machine.wait_idle()
            started = await rpc(api, "job.start", name="cut.nc")  # idle now: it may start
            await api.close()
            await line_socket.close()
        sender.close()
        other.close()
    assert refused_api["error"]["code"] == 45, refused_api
    assert refused_ws == "error:45"
    assert other.received.replies() == ["error:45"]
    assert sender.received.replies() == ["ok"] * (moves + 1), "the stream was never cut"
    assert started["result"]["state"] == "running", started
