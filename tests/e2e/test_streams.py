"""The same scenarios over TCP, WebSocket and the pty, with real sockets and a real pty."""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import RealClock
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc

BANNER = "Grbl 1.1h ['$' for help]"


class Client:
    """A line client over one transport: send bytes, read lines with a timeout."""

    def __init__(self) -> None:
        self.buffer = ""

    async def send(self, data: bytes) -> None:
        raise NotImplementedError

    async def receive(self) -> str:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def line(self, timeout_s: float = 5.0) -> str:
        while "\n" not in self.buffer:
            self.buffer += await asyncio.wait_for(self.receive(), timeout_s)
        line, _, self.buffer = self.buffer.partition("\n")
        return line.rstrip("\r")

    async def lines_until(self, last: str, timeout_s: float = 5.0) -> list[str]:
        got: list[str] = []
        while not got or got[-1] != last:
            line = await self.line(timeout_s)
            if line:
                got.append(line)
        return got

    async def reply(self, text: str) -> list[str]:
        """Send a line; everything up to and including its ok/error (status pushes skipped)."""
        await self.send(text.encode() + b"\n")
        got: list[str] = []
        while True:
            line = await self.line()
            if not line or line.startswith("<") or line == BANNER:
                continue
            got.append(line)
            if line == "ok" or line.startswith("error:"):
                return got


class TcpClient(Client):
    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        super().__init__()
        self.reader, self.writer = reader, writer

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def receive(self) -> str:
        data = await self.reader.read(4096)
        if not data:
            raise ConnectionError("closed")
        return data.decode()

    async def close(self) -> None:
        self.writer.close()


class WsClient(Client):
    def __init__(self, socket: wsc.ClientConnection) -> None:
        super().__init__()
        self.socket = socket

    async def send(self, data: bytes) -> None:
        await self.socket.send(data.decode("latin-1"))

    async def receive(self) -> str:
        message = await self.socket.recv()
        return message if isinstance(message, str) else message.decode()

    async def close(self) -> None:
        await self.socket.close()


class PtyClient(Client):
    def __init__(self, path: Path) -> None:
        super().__init__()
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self.readable = asyncio.Event()
        asyncio.get_running_loop().add_reader(self.fd, self.readable.set)

    async def send(self, data: bytes) -> None:
        os.write(self.fd, data)

    async def receive(self) -> str:
        while True:
            try:
                return os.read(self.fd, 4096).decode()
            except BlockingIOError:
                self.readable.clear()
                await self.readable.wait()

    async def close(self) -> None:
        asyncio.get_running_loop().remove_reader(self.fd)
        os.close(self.fd)


@pytest.fixture(params=["tcp", "websocket", "pty"])
async def connect(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator:
    kind = request.param
    config = make_config(serial={"pty": str(tmp_path / "ttyMotiond")},
                         jobs={"data_dir": str(tmp_path / "jobs")})
    app = App(config, clock=RealClock(),
              transports=[TcpTransport, http_with_api, SerialTransport])
    task = asyncio.create_task(app.run())
    await asyncio.wait_for(app.ready.wait(), 5)
    tcp, http, _ = app.transports
    clients: list[Client] = []

    async def open_client() -> Client:
        if kind == "tcp":
            client: Client = TcpClient(*await asyncio.open_connection("127.0.0.1", tcp.port))
        elif kind == "websocket":
            socket = await wsc.connect(f"ws://127.0.0.1:{http.port}/ws")
            client = WsClient(socket)
        else:
            client = PtyClient(tmp_path / "ttyMotiond")
        clients.append(client)
        return client

    open_client.app = app  # type: ignore[attr-defined]
    yield open_client
    for client in clients:
        with contextlib.suppress(OSError, ConnectionError, wsc.ConnectionClosed):
            await client.close()
    app.request_stop()
    await asyncio.wait_for(task, 5)


async def test_banner_on_connect_and_one_reply_per_line_in_order(connect) -> None:
    client = await connect()
    if not isinstance(client, PtyClient):  # the pty greets on its first byte
        assert BANNER in await client.lines_until(BANNER)
    await client.send(b"G21\r\nG90\n\n(comment)\r$G\nG1 X\n")
    replies: list[str] = []
    while len(replies) < 7:
        line = await client.line()
        if line and line != BANNER:
            replies.append(line)
    assert replies == ["ok", "ok", "ok", "ok", "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]", "ok",
                       "error:2"]


async def test_status_report_answers_at_once_even_inside_a_line(connect) -> None:
    client = await connect()
    await client.send(b"G0 X1?0\n")
    lines = [await client.line() for _ in range(3)]
    status = [line for line in lines if line.startswith("<")]
    assert status, lines
    assert status[0].split("|")[0] in ("<Idle", "<Run")
    assert status[0].split("|")[1].startswith("MPos:")
    while "ok" not in lines:
        lines.append(await client.line())
    assert lines.count("ok") == 1


async def test_long_line_garbage_and_unknown_code_then_the_next_line_works(connect) -> None:
    client = await connect()
    assert (await client.reply("G1 X1 " + "Y1" * 300))[-1] == "error:11"
    await client.send(b"\xff\xfe\x00\x01\n")
    assert await client.line() in ("error:1", BANNER, "")
    assert (await client.reply("G81 X50 Y60 Z-5 R1"))[-1] == "error:20"
    assert await client.reply("G0 X2") == ["ok"]


async def test_hold_and_resume_finish_at_the_exact_end(connect) -> None:
    client = await connect()
    app = connect.app
    assert await client.reply("G1 X40 F1200") == ["ok"]
    await asyncio.sleep(0.5)
    await client.send(b"!")
    await asyncio.sleep(0.3)
    await client.send(b"?")
    status = await client.line()
    while not status.startswith("<"):
        status = await client.line()
    assert status.startswith("<Hold:0|")
    x_held = app.kernel.machine.stepgen.state.position_mm[0]
    assert 0 < x_held < 40
    await client.send(b"~")
    await app.kernel.machine.wait_idle()
    assert app.kernel.machine.backend.steps[0] == 40 * 80


async def test_ctrl_x_resets_and_greets_again(connect) -> None:
    client = await connect()
    assert await client.reply("G0 X3") == ["ok"]
    await client.send(b"\x18")
    assert BANNER in await client.lines_until(BANNER)
    unlock = await client.reply("$X")
    assert unlock[-1] == "ok"
    assert (await client.reply("G0 X0"))[-1] == "ok"
    assert connect.app.kernel.state.value in ("Idle", "Run")


async def test_m112_halts_the_moment_it_arrives_even_behind_waiting_lines(connect) -> None:
    client = await connect()
    app = connect.app
    await client.send(b"".join(b"G1 X%d F300\n" % (i % 2 * 50) for i in range(40)) + b"M112\n")
    for _ in range(50):
        if app.kernel.alarm_code:
            break
        await asyncio.sleep(0.02)
    assert app.kernel.alarm_code == 40
    assert not app.kernel.machine.stepgen.state.moving
    assert len(app.kernel.machine.planner) == 0
