"""Hostile clients on the line protocol, against the strictest setup (a token; connections that
have not logged in read-only or refused), over real TCP sockets, a real pty and real WebSockets:
logging in from an observer, guessing tokens, flooding '?', streaming ahead without character
counting, holding every connection slot, job names that break lines, stale files."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import subprocess
import sys
import time
import tty
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from server.api.server import http_with_api
from server.app import App
from server.errors import ConfigError
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport
from server.transports.websocket import HttpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running

TOKEN = "s3cret-token"
BANNER = "Grbl 1.1h ['$' for help]"


class Lines:
    """Every line a connection receives, collected in the background."""

    def __init__(self, read: Callable[[], Awaitable[bytes]]) -> None:
        self.lines: list[str] = []
        self.ended = False
        self._changed = asyncio.Event()
        self._task = asyncio.create_task(self._collect(read))

    async def _collect(self, read: Callable[[], Awaitable[bytes]]) -> None:
        buffer = b""
        try:
            while chunk := await read():
                buffer += chunk
                *complete, buffer = buffer.split(b"\n")
                self.lines += [line.decode("utf-8", "replace").rstrip("\r") for line in complete]
                self._changed.set()
        except (ConnectionError, OSError):
            pass
        finally:
            self.ended = True
            self._changed.set()

    async def until(self, done: Callable[[list[str]], bool], timeout_s: float = 5.0) -> list[str]:
        """Wait until ``done(lines)``; the lines so far."""
        async with asyncio.timeout(timeout_s):
            while not done(self.lines):
                if self.ended:
                    raise AssertionError(f"connection ended; got {self.lines[-8:]}")
                self._changed.clear()
                await self._changed.wait()
        return self.lines

    async def until_ended(self, timeout_s: float = 5.0) -> list[str]:
        async with asyncio.timeout(timeout_s):
            while not self.ended:
                self._changed.clear()
                await self._changed.wait()
        return self.lines

    async def more(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for one more line."""
        count = len(self.lines)
        with contextlib.suppress(TimeoutError):
            await self.until(lambda got: len(got) > count, timeout_s)

    def replies(self) -> list[str]:
        return [line for line in self.lines if line == "ok" or line.startswith("error:")]

    def stop(self) -> None:
        self._task.cancel()


class Tcp:
    """A raw TCP client."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.received = Lines(lambda: reader.read(65536))

    @classmethod
    async def open(cls, port: int) -> Tcp:
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def send(self, data: bytes) -> None:
        self.writer.write(data)

    def close(self) -> None:
        self.received.stop()
        self.writer.transport.abort()


class Pty:
    """A serial-only sender on the pty motiond links."""

    def __init__(self, path: Path) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)
        self._readable = asyncio.Event()
        asyncio.get_running_loop().add_reader(self.fd, self._readable.set)
        self.received = Lines(self._read)

    async def _read(self) -> bytes:
        while True:
            try:
                return os.read(self.fd, 65536)
            except BlockingIOError:
                self._readable.clear()
                await self._readable.wait()

    async def send(self, data: bytes) -> None:
        """All of ``data``, as fast as the terminal takes it (no character counting)."""
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(self.fd, view[:4096]):]
            except BlockingIOError:
                await asyncio.sleep(0.001)

    def close(self) -> None:
        self.received.stop()
        asyncio.get_running_loop().remove_reader(self.fd)
        os.close(self.fd)


class Ws:
    """A /ws client sending bytes as binary messages (the byte path, message ends ending
    lines), each at most ``MESSAGE_BYTES`` and ending at a line end when it can."""

    MESSAGE_BYTES = 32 << 10

    def __init__(self, http: aiohttp.ClientSession, socket: aiohttp.ClientWebSocketResponse):
        self.http, self.socket = http, socket
        self.received = Lines(self._read)

    @classmethod
    async def open(cls, port: int) -> Ws:
        http = aiohttp.ClientSession()
        return cls(http, await http.ws_connect(f"http://127.0.0.1:{port}/ws"))

    async def _read(self) -> bytes:
        message = await self.socket.receive()
        return message.data.encode() if message.type is aiohttp.WSMsgType.TEXT else b""

    async def send(self, data: bytes) -> None:
        while data:
            cut = data.rfind(b"\n", 0, self.MESSAGE_BYTES) + 1 or self.MESSAGE_BYTES
            await self.socket.send_bytes(data[:cut])
            data = data[cut:]

    def close(self) -> None:
        self.received.stop()
        asyncio.get_running_loop().create_task(self.http.close())


def strict(**sections: Any) -> Any:
    """The strictest config: a token; connections that have not logged in may only watch."""
    protocol = {"token": TOKEN, "unauthenticated": "read-only", **sections.pop("protocol", {})}
    return make_config(protocol=protocol, **sections)


def tcp_port(app: App) -> int:
    return next(t.port for t in app.transports if isinstance(t, TcpTransport))


def http_port(app: App) -> int:
    return next(t.port for t in app.transports if isinstance(t, HttpTransport))


def is_status(line: str) -> bool:
    return line.startswith("<")


# -- 1. an observer stays an observer -----------------------------------------------------------
@pytest.mark.parametrize("token", [None, TOKEN])
async def test_auth_on_an_observer_socket_never_grants_control(token: str | None) -> None:
    config = make_config(protocol={"token": token}) if token else make_config()
    async with running(config, transports=[http_with_api]) as app:
        query = f"mode=observe&token={token}" if token else "mode=observe"
        url = f"ws://127.0.0.1:{http_port(app)}/ws?{query}"
        async with wsc.connect(url) as socket:
            await socket.send(f"$AUTH={token or 'anything'}\nG0 X5\n!")
            frames: list[str] = []
            while sum(f.startswith(("ok", "error")) for f in frames) < 2:
                frames.append((await asyncio.wait_for(socket.recv(), 5)).strip())
        assert [f for f in frames if f.startswith(("ok", "error"))] == ["error:46", "error:46"]
        assert app.kernel.machine.planner.position_mm == (0.0, 0.0, 0.0)
        assert app.kernel.state is MachineState.IDLE


# -- 2. guessing the token --------------------------------------------------------------------
async def test_wrong_tokens_are_slowed_per_address_capped_per_connection_and_summarised(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="motiond.auth")
    config = strict(protocol={"auth_delay_s": 0.1, "auth_max_delay_s": 2.0,
                              "auth_failures_per_connection": 3})
    async with running(config, transports=[TcpTransport]) as app:
        guesser = await Tcp.open(tcp_port(app))
        started_s = time.monotonic()
        guesses = ["$AUTH=ünïcødé-€-😀", *(f"$AUTH=guess-{n}" for n in range(9))]
        await guesser.send("".join(g + "\n" for g in guesses).encode())
        lines = await guesser.received.until_ended(timeout_s=10)
        assert guesser.received.replies() == ["error:46"] * 3  # then the connection is closed
        assert "closing the connection" in lines[-1]
        assert time.monotonic() - started_s >= 0.1 + 0.2 + 0.4  # doubling delays
        second = await Tcp.open(tcp_port(app))  # same address: the 4th failure waits 0.8 s
        started_s = time.monotonic()
        await second.send(b"$AUTH=guess-again\n")
        await second.received.until(lambda got: "error:46" in got)
        assert time.monotonic() - started_s >= 0.75
        await second.send(f"$AUTH={TOKEN}\nG0 X1\n".encode())
        await second.received.until(lambda got: got.count("ok") == 2)
        assert app.kernel.state is not MachineState.ALARM  # non-ASCII: a clean error only
        second.close()
    messages = [r.getMessage() for r in caplog.records if r.name == "motiond.auth"]
    assert len(messages) == 2, messages  # one line when the burst begins, one summary
    assert "wrong token from 127.0.0.1" in messages[0]
    assert messages[1].startswith("3 more wrong tokens from 127.0.0.1 (4 in this burst)")


# -- 3a. a flood of '?' -----------------------------------------------------------------------
async def test_a_status_flood_gets_paced_reports_and_other_clients_stay_prompt() -> None:
    """The flooder may not control: its input is read at its paced rate (what it sends beyond
    that waits unread in the socket buffers), so it gets few reports; the other stays prompt."""
    async with running(strict(), transports=[TcpTransport]) as app:
        flooder, other = await Tcp.open(tcp_port(app)), await Tcp.open(tcp_port(app))
        flood_s = 1.0
        started_s = time.monotonic()
        latencies_s: list[float] = []
        while time.monotonic() - started_s < flood_s:
            for _ in range(8):
                flooder.writer.write(b"?" * 4096)  # no drain: the server reads it slowly
            before = len([line for line in other.received.lines if is_status(line)])
            asked_s = time.monotonic()
            await other.send(b"?")
            await other.received.until(
                lambda got, n=before: len([line for line in got if is_status(line)]) > n)
            latencies_s.append(time.monotonic() - asked_s)
        elapsed_s = time.monotonic() - started_s
        await asyncio.sleep(0.3)
        reports = [line for line in flooder.received.lines if is_status(line)]
        protocol = app.kernel.config.core.protocol
        examined_bytes = protocol.read_only_input_bytes_per_s * (elapsed_s + 0.3) + 1024
        assert 0 < len(reports) <= examined_bytes / 256 + 1, len(reports)  # a report a read
        assert max(latencies_s) < 0.5, max(latencies_s)
        flooder.close()
        other.close()


# -- 3b. a sender streaming ahead without character counting ------------------------------------
@pytest.fixture(params=["tcp", "pty", "ws"])
async def sender(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator[Any]:
    link = tmp_path / "ttyMotiond"
    config = make_config(
        axes={"x": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000,
                    "max_mm": 100_000}},
        serial={"pty": str(link)})
    async with running(config, clock=RealClock(),
                       transports=[TcpTransport, SerialTransport, HttpTransport]) as app:
        client: Tcp | Pty | Ws
        if request.param == "tcp":
            client = await Tcp.open(tcp_port(app))
        elif request.param == "ws":
            client = await Ws.open(http_port(app))
        else:
            client = Pty(link)
        yield app, client
        client.close()


async def test_hold_and_reset_act_at_once_behind_two_megabytes_streamed_ahead(sender) -> None:
    """On every transport, /ws included (a hold there used to wait behind the lines queued in
    front of it: 6.2 s behind 100 lines, never behind 400)."""
    app, client = sender
    held = asyncio.Event()
    app.kernel.events.subscribe(
        "state", lambda state: held.set() if state is MachineState.HOLD else None)
    move = b"G1 X0.010 F60\n"  # 10 ms each: the machine is far slower than the stream
    async with asyncio.timeout(10):  # not behind 2 MB of moves (hours at this feed)
        await client.send(b"G91\n" + move * (2_000_000 // len(move)))
        await client.send(b"!")
        await held.wait()
    async with asyncio.timeout(5):  # Hold:1 while it decelerates, then Hold:0
        while not any(line.startswith("<Hold:0") for line in client.received.lines):
            await client.send(b"?")
            await client.received.more(timeout_s=0.1)
    acknowledged = client.received.lines.count("ok") - 1  # G91's ok
    assert acknowledged > 0
    planned_x = app.kernel.machine.planner.position_mm[0]
    assert abs(planned_x - 0.01 * acknowledged) < 0.005  # each acknowledged move once, no other
    banners = client.received.lines.count(BANNER)  # the connection's own
    await client.send(b"\x18")  # (what follows it in the same read is flushed, as by Grbl)
    await client.received.until(lambda got: got.count(BANNER) > banners, timeout_s=5)
    oks_before = client.received.lines.count("ok")
    await client.send(b"$X\nG4 P0.01\n")
    await client.received.until(lambda got: got.count("ok") >= oks_before + 2)
    await asyncio.sleep(0.3)  # nothing held back before the reset runs after it
    assert client.received.replies()[-2:] == ["ok", "ok"]
    assert client.received.lines.count("ok") == oks_before + 2
    position = app.kernel.machine.stepgen.state.position_mm
    assert app.kernel.machine.planner.position_mm == pytest.approx(position)
    assert position[0] <= 0.01 * acknowledged + 1e-9


async def test_realtime_bytes_held_back_act_once_and_as_the_protocol_reads_them(sender) -> None:
    app, client = sender
    await client.send(b"G91\nG1 X0.6 F60\nG1 X0.6 F60\n")  # 1.2 s: fills the planner
    await client.received.until(lambda got: got.count("ok") == 3)
    await client.send(b"!")  # held: nothing drains while the stream below arrives
    move = b"G1 X0.010 F6000\n"
    moves = 4000
    stream = move * (moves // 2) + b"\x91(\xc5\x91 is \xc5\x91, not 0x91)\n" + move * (moves // 2)
    async with asyncio.timeout(10):
        await client.send(stream)
        while app.kernel.machine.feed_override != 110:  # seen while held back, not later
            await client.received.more(timeout_s=0.05)
    await client.send(b"~")
    await client.received.until(lambda got: got.count("ok") == 3 + moves + 1, timeout_s=20)
    assert app.kernel.machine.feed_override == 110  # once: not again when the bytes are fed
    assert client.received.replies() == ["ok"] * (3 + moves + 1)
    assert app.kernel.machine.planner.position_mm[0] == pytest.approx(1.2 + 0.01 * moves)


# -- 4. idle sockets and reserved slots -----------------------------------------------------------
async def test_idle_connections_that_never_log_in_are_closed_and_the_operator_gets_in() -> None:
    config = strict(tcp={"idle_timeout_s": 0.3, "reserved_connections": 0})
    async with running(config, transports=[TcpTransport]) as app:
        port = tcp_port(app)
        operator = await Tcp.open(port)
        await operator.send(f"$AUTH={TOKEN}\n".encode())
        await operator.received.until(lambda got: "ok" in got)
        squatters = [await Tcp.open(port) for _ in range(15)]
        for squatter in squatters:
            lines = await squatter.received.until_ended(timeout_s=5)
            assert "idle for 0.3 s without logging in" in lines[-1]
        late = await Tcp.open(port)
        await late.send(f"$AUTH={TOKEN}\nG0 X1\n".encode())
        await late.received.until(lambda got: got.count("ok") == 2)
        await asyncio.sleep(0.5)  # logged in: an idle sender keeps its connection
        await operator.send(b"?")
        await operator.received.until(lambda got: any(is_status(line) for line in got))
        assert not operator.received.ended
        for client in (operator, late, *squatters):
            client.close()


async def test_without_a_token_only_connections_that_never_sent_a_byte_time_out() -> None:
    async with running(make_config(tcp={"idle_timeout_s": 0.3}), transports=[TcpTransport]) as app:
        silent, sender = await Tcp.open(tcp_port(app)), await Tcp.open(tcp_port(app))
        await sender.send(b"?")
        lines = await silent.received.until_ended()
        assert "nothing received for 0.3 s" in lines[-1]
        await asyncio.sleep(0.5)
        await sender.send(b"G0 X1\n")
        await sender.received.until(lambda got: "ok" in got)
        assert not sender.received.ended
        silent.close()
        sender.close()


async def test_reserved_slots_keep_room_for_the_token_holder() -> None:
    config = strict(tcp={"max_connections": 4, "reserved_connections": 1,
                         "login_timeout_s": 0.5})
    async with running(config, transports=[TcpTransport]) as app:
        port = tcp_port(app)
        watchers = [await Tcp.open(port) for _ in range(3)]  # the unauthenticated slots
        for watcher in watchers:
            await watcher.send(b"?")
            await watcher.received.until(lambda got: any(is_status(line) for line in got))
        intruder = await Tcp.open(port)  # gets the reserved slot on probation
        await intruder.send(b"G0 X1\n")
        lines = await intruder.received.until_ended()
        assert intruder.received.replies() == ["error:46"] and "reserved" in lines[-1]
        slow = await Tcp.open(port)
        assert "no $AUTH=<token> within 0.5 s" in (await slow.received.until_ended())[-1]
        squatter = await Tcp.open(port)
        await squatter.received.until(lambda got: BANNER in got)
        operator = await Tcp.open(port)  # every slot taken: replaces the one on probation
        assert "a newer connection took" in (await squatter.received.until_ended())[-1]
        await operator.send(f"$AUTH={TOKEN}\nG0 X1\n".encode())
        await operator.received.until(lambda got: got.count("ok") == 2)
        refused = await Tcp.open(port)
        assert "too many connections" in (await refused.received.until_ended())[-1]
        assert app.kernel.machine.planner.position_mm[0] == 1.0
        for client in (*watchers, intruder, slow, squatter, operator, refused):
            client.close()


# -- 5. job names that break lines ---------------------------------------------------------------
async def test_job_names_with_line_breaks_are_refused_and_never_listed() -> None:
    config = strict(http={"token": TOKEN})
    async with running(config, transports=[TcpTransport, http_with_api]) as app:
        data_dir = app.kernel.jobs.jobs_dir
        data_dir.mkdir(parents=True, exist_ok=True)
        for name in ("a.nc", "evil\u2028ok\u2028.nc", "evil\rok.nc", "x\x85y.nc"):
            (data_dir / name).write_text("G0 X1\n")
        base = f"http://127.0.0.1:{http_port(app)}"
        async with aiohttp.ClientSession() as http:
            for name in ("up\nok", "up\u2029ok", "up\x0bok", "up\x1cok", "up\x1b[2J"):
                async with http.post(f"{base}/upload", params={"name": name, "token": TOKEN},
                                     data=b"G0 X1\n") as response:
                    body = await response.json()
                assert response.status == 400 and "line breaks" in body["error"]["message"]
        async with wsc.connect(f"ws://127.0.0.1:{http_port(app)}/api?token={TOKEN}") as api:
            await api.send(json.dumps({"jsonrpc": "2.0", "id": 1, "method": "job.upload",
                                       "params": {"name": "x\u2028ok", "text": "G0 X1\n"}}))
            assert "line breaks" in json.loads(await asyncio.wait_for(api.recv(), 5))[
                "error"]["message"]
            await api.send(json.dumps({"jsonrpc": "2.0", "id": 2, "method": "job.list"}))
            listed = json.loads(await asyncio.wait_for(api.recv(), 5))["result"]
            assert [job["name"] for job in listed] == ["a.nc"]
        assert sorted(p.name for p in data_dir.iterdir() if p.name.startswith("up")) == []
        async with wsc.connect(f"ws://127.0.0.1:{http_port(app)}/ws?token={TOKEN}") as ws:
            await ws.send("ls\n")
            frames = [(await asyncio.wait_for(ws.recv(), 5)).strip() for _ in range(3)]
        assert frames[1:] == ["a.nc", "ok"]
        client = await Tcp.open(tcp_port(app))
        await client.send(f"$AUTH={TOKEN}\nls\nG0 X1\n".encode())
        lines = await client.received.until(lambda got: got.count("ok") == 3)
        assert lines[lines.index("ok") + 1:] == ["a.nc", "ok", "ok"]
        assert app.kernel.state is not MachineState.ALARM
        client.close()


# -- 6. stale files ------------------------------------------------------------------------------
async def test_uploads_interrupted_by_a_crash_are_removed_at_start_up(tmp_path: Path) -> None:
    data_dir = tmp_path / "jobs"
    data_dir.mkdir()  # the job files of the data folder tmp_path
    (data_dir / ".upload-k2j3h4").write_bytes(b"G0 X1\n" * 1000)
    (data_dir / "kept.nc").write_text("G0 X1\n")
    outside = tmp_path / "not-ours.txt"
    outside.write_text("precious")
    (data_dir / ".upload-link").symlink_to(outside)
    async with running(make_config(jobs={"data_dir": str(tmp_path)}), transports=[]):
        assert sorted(p.name for p in data_dir.iterdir()) == [".upload-link", "kept.nc"]
    assert outside.read_text() == "precious"


@pytest.mark.parametrize("kind", ["file", "link to a file", "folder"])
def test_the_pty_path_never_replaces_a_users_file(tmp_path: Path, kind: str) -> None:
    target = tmp_path / "important.txt"
    target.write_text("keep me")
    path = tmp_path / "ttyMotiond"
    if kind == "file":
        path.write_text("keep me too")
    elif kind == "link to a file":
        path.symlink_to(target)
    else:
        path.mkdir()
    with pytest.raises(ConfigError, match="is not a link to a pseudo-terminal left by motiond"):
        App(make_config(serial={"pty": str(path)}), transports=[SerialTransport])
    assert target.read_text() == "keep me"
    if kind == "file":
        assert path.read_text() == "keep me too"
    elif kind == "link to a file":
        assert path.is_symlink() and os.readlink(path) == str(target)
    else:
        assert path.is_dir()


def test_motiond_with_a_pty_path_on_a_users_file_exits_with_a_clear_message(
    tmp_path: Path,
) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("keep me")
    argv = ["--pty", str(path), "--data-dir", str(tmp_path / "jobs"), "--tcp-port", "0",
            "--http-port", "0"]
    try:
        done = subprocess.run([sys.executable, "-m", "server.cli", *argv], capture_output=True,
                              text=True, timeout=30, check=False)
    finally:
        assert path.read_text() == "keep me"
    assert done.returncode == 2
    assert f"{path} exists and is not a link to a pseudo-terminal" in done.stderr


async def test_a_stale_pty_link_from_an_earlier_run_is_replaced(tmp_path: Path) -> None:
    path = tmp_path / "ttyMotiond"
    path.symlink_to("/dev/pts/987654")
    async with running(make_config(serial={"pty": str(path)}), transports=[SerialTransport]):
        client = Pty(path)
        await client.send(b"?")
        await client.received.until(lambda got: any(is_status(line) for line in got))
        client.close()
    assert not path.exists() and not path.is_symlink()
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
