"""Jobs never take the machine from someone else, and never hold a whole file in memory.

A 50 MB job (2.9 M short lines) is planned before it starts (its fit decides whether anything
moves) reading the file through in a thread: the server's memory grows by far less than the
file (a 200 MB file used to take 2.98 GB), ``?`` is answered throughout, the first move follows
``job.start``'s answer within a second, and ``job.abort`` ends the job's reading too.

A job starts only when the machine is idle and nobody else is using it: ``job.start`` on the
JSON API, ``play`` on TCP and on /ws (and MQTT's ``cmd/job``, which calls the same
:meth:`Jobs.play`) all answer 45 while a sender's stream runs, and the sender's lines all run.
Real sockets and real WebSocket clients (aiohttp's) against a server in this process.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path
from typing import Any

import aiohttp

from server.api.server import http_with_api
from server.paths import jobs_dir
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.e2e.test_hostile_lines import Tcp, http_port, tcp_port
from tests.e2e.test_mqtt import MACHINE, PREFIX, is_online, mpos, tcp_report
from tests.support.broker import mosquitto, mqtt_toml, watching
from tests.support.helpers import running
from tests.support.processes import motiond

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
        jobs_dir(config.core).mkdir(parents=True, exist_ok=True)
        (jobs_dir(config.core) / "cut.nc").write_text(JOB)
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


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def write_big_job(path: Path, size_mb: int) -> None:
    """Moves of about 240 characters a line (a comment pads each), so that the plan of a file
    this size takes seconds, not minutes, on a loaded CI machine: the line count's own bound
    (the plan's timeline) is tested in tests/unit/test_job_plan_memory.py."""
    pad = b" (" + b"padding to make a long line of a CAM program's comment " * 4 + b")"
    block = (b"G1 X1 F6000" + pad + b"\nG1 X0" + pad + b"\n") * 5_000
    with path.open("wb") as handle:
        for _ in range(size_mb * (1 << 20) // len(block) + 1):
            handle.write(block)


async def status_round_trips_s(port: int, until: asyncio.Future[Any]) -> list[float]:
    """``?`` round trips on one TCP connection, every 50 ms until ``until`` is done."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    times: list[float] = []
    try:
        await asyncio.wait_for(reader.readuntil(b"for help]"), 5)
        while not until.done():
            sent_s = time.monotonic()
            writer.write(b"?")
            await asyncio.wait_for(reader.readuntil(b">"), 5)
            times.append(time.monotonic() - sent_s)
            await asyncio.sleep(0.05)
    finally:
        writer.close()
    return times


async def test_a_50_mb_job_is_placed_in_bounded_memory_without_stalling_then_moves_at_once(
    tmp_path: Path,
) -> None:
    """A job is planned whole before it may start (its fit decides whether anything moves):
    ``job.place`` (the UI's preview) reads the file through in a thread, so memory stays
    bounded and ``?`` is answered throughout; ``job.start`` then reuses that plan and the
    first move comes within a second; ``job.abort`` ends the job and its reading."""
    async with motiond(tmp_path) as served:
        pid = served.process.pid
        write_big_job(served.jobs_dir / "big.nc", 50)
        await asyncio.sleep(0.5)
        rss_before_mb = rss_mb(pid)
        peak_mb = rss_before_mb
        async with aiohttp.ClientSession() as http:
            api = await http.ws_connect(f"http://{served.http}/api")
            placing = asyncio.ensure_future(rpc_slow(api, "job.place", name="big.nc"))
            probe = asyncio.ensure_future(status_round_trips_s(served.tcp_port, placing))
            while not placing.done():
                peak_mb = max(peak_mb, rss_mb(pid))
                await asyncio.sleep(0.2)
            placed, round_trips_s = placing.result(), await probe
            started_s = time.monotonic()
            started = await rpc(api, "job.start", name="big.nc")  # placed: its plan is kept
            answered_s = time.monotonic()
            while mpos(await tcp_report(served.tcp_port))[0] == 0.0:
                assert time.monotonic() - answered_s < 5, "no motion"
            first_move_s = time.monotonic() - started_s
            for _ in range(10):  # 2 s of the job
                peak_mb = max(peak_mb, rss_mb(pid))
                await asyncio.sleep(0.2)
            aborted = await rpc(api, "job.abort")
            await asyncio.sleep(0.5)
            cpu_before_s, window_start_s = cpu_s(pid), time.monotonic()
            await asyncio.sleep(2.0)
            cpu_share = (cpu_s(pid) - cpu_before_s) / (time.monotonic() - window_start_s)
            await api.close()
    assert placed["result"]["fits"] is True, placed
    assert started["result"]["state"] == "running", started
    assert started["result"]["lines_total"] > 200_000, started  # the plan read it all
    assert round_trips_s and max(round_trips_s) < 0.5, max(round_trips_s)
    assert first_move_s < 1.0, first_move_s
    assert peak_mb - rss_before_mb < 60, (rss_before_mb, peak_mb)  # the file was 50 MB
    assert aborted["result"]["state"] == "aborted", aborted
    assert cpu_share < 0.5, f"the job went on reading after the abort: {cpu_share:.0%} of a CPU"


async def rpc_slow(socket: aiohttp.ClientWebSocketResponse, method: str, **params: Any) -> Any:
    """:func:`rpc` for a request that may take a while (a big job's plan on a loaded host)."""
    await socket.send_str(json.dumps({"jsonrpc": "2.0", "id": 2, "method": method,
                                      "params": params}))
    async with asyncio.timeout(300):
        while True:
            message = json.loads((await socket.receive()).data)
            if message.get("id") == 2:
                return message


async def test_an_mqtt_job_command_never_cuts_a_senders_stream(tmp_path: Path) -> None:
    async with (
        mosquitto(tmp_path / "broker") as broker,
        motiond(tmp_path, MACHINE + mqtt_toml(broker, allow_control=True)) as served,
        watching(broker, f"{PREFIX}/#") as watch,
    ):
        (served.jobs_dir / "cut.nc").write_text(JOB)
        await watch.wait_for(f"{PREFIX}/availability", is_online, timeout_s=15)
        sender = await Tcp.open(served.tcp_port)
        moves = 20
        await sender.send(b"G91\n" + b"G1 X1 F600\n" * moves)  # 2 s of motion
        await sender.received.until(lambda got: got.count("ok") >= 3)
        await watch.publish(f"{PREFIX}/cmd/job", {"id": "j", "name": "cut.nc"})
        refused = await watch.wait_json(f"{PREFIX}/reply", lambda r: r["id"] == "j")
        await sender.received.until(lambda got: got.count("ok") == moves + 1, 10)
        sender.close()
    assert refused["ok"] is False and refused["error"]["code"] == 45, refused
    assert sender.received.replies() == ["ok"] * (moves + 1), "the stream was never cut"
