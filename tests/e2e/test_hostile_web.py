"""Hostile clients against the HTTP port in its strictest config (a token set, connections
without it read-only): observers stay observers, rebinding hosts are refused, one frame cannot
freeze the loop or grow memory, malformed JSON and tokens get clean errors, idle and half-sent
connections cannot lock the operator out. Real sockets and real WebSocket clients throughout;
the compressed frame is built by hand so its size on the wire is known."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import sys
import zlib
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest

from server.api.server import http_with_api
from server.app import App
from server.transports.tcp import TcpTransport
from tests.conftest import REPO, make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running

TOKEN = "s3cret-token"
MIB = 1 << 20


@contextlib.asynccontextmanager
async def serve(**http: Any) -> AsyncIterator[tuple[App, int, int]]:
    """A server with the token on every port; yields it, its TCP port and its HTTP port."""
    config = make_config(protocol={"token": TOKEN, "unauthenticated": "read-only"},
                         http={"token": TOKEN, **http})
    async with running(config, transports=[TcpTransport, http_with_api]) as app:
        tcp, web = app.transports
        yield app, tcp.port, web.port  # type: ignore[attr-defined]


async def call(socket: Any, method: str, request_id: int = 1, **params: Any) -> dict[str, Any]:
    await socket.send(json.dumps({"jsonrpc": "2.0", "id": request_id, "method": method,
                                  "params": params}))
    return await answer(socket)


async def answer(socket: Any) -> dict[str, Any]:
    """The next response (notifications skipped)."""
    while True:
        message = json.loads(await asyncio.wait_for(socket.recv(), 10))
        if "id" in message:
            return message  # type: ignore[no-any-return]


async def close_code(socket: Any) -> int | None:
    """Wait (bounded) for a websockets connection to end; the code the server closed with."""
    with contextlib.suppress(wsc.ConnectionClosed):
        async with asyncio.timeout(15):
            while True:
                await socket.recv()
    return socket.close_code  # type: ignore[no-any-return]


async def http_status(port: int, head: str) -> int:
    """The status of one raw HTTP/1.1 request (``head`` without the final blank line)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(head.encode("utf-8", "surrogateescape") + b"Connection: close\r\n\r\n")
    try:
        status_line = await asyncio.wait_for(reader.readline(), 10)
    finally:
        writer.close()
    return int(status_line.split()[1])


async def ws_handshake(
    port: int, path: str, extra: bytes = b""
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, bytes]:
    """A WebSocket opening handshake by hand; the response head."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    key = base64.b64encode(os.urandom(16))
    writer.write(b"GET " + path.encode() + b" HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n" % port
                 + b"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
                 + b"Sec-WebSocket-Key: " + key + b"\r\n" + extra + b"\r\n")
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
    return reader, writer, head


def client_frame(payload: bytes, *, compressed: bool = False) -> bytes:
    """One masked text frame (RSV1 set: permessage-deflate compressed)."""
    head = bytes([0x80 | (0x40 if compressed else 0) | 0x1])
    size = len(payload)
    if size < 126:
        head += bytes([0x80 | size])
    elif size < 1 << 16:
        head += bytes([0x80 | 126]) + size.to_bytes(2, "big")
    else:
        head += bytes([0x80 | 127]) + size.to_bytes(8, "big")
    mask = os.urandom(4)
    keystream = (mask * (size // 4 + 1))[:size]
    masked = (int.from_bytes(payload, "big") ^ int.from_bytes(keystream, "big"))
    return head + mask + masked.to_bytes(size, "big")


async def server_frame(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """The next frame from the server: its opcode and payload."""
    first, second = await asyncio.wait_for(reader.readexactly(2), 15)
    size = second & 0x7F
    if size >= 126:
        size = int.from_bytes(await reader.readexactly(2 if size == 126 else 8), "big")
    return first & 0x0F, await reader.readexactly(size)


class StatusPoller:
    """An operator on TCP who logged in and polls ``?``: the times its reports arrived."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.times: list[float] = []
        self.stop = asyncio.Event()
        self.polling = asyncio.Event()
        self.task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        writer.write(f"$AUTH={TOKEN}\n".encode())
        while (await asyncio.wait_for(reader.readline(), 10)).strip() != b"ok":
            pass
        loop = asyncio.get_running_loop()
        while not self.stop.is_set():
            writer.write(b"?")
            while not (await asyncio.wait_for(reader.readline(), 30)).startswith(b"<"):
                pass
            self.times.append(loop.time())
            if len(self.times) >= 3:
                self.polling.set()
            await asyncio.sleep(0.02)
        writer.close()

    async def started(self) -> None:
        await asyncio.wait_for(self.polling.wait(), 30)

    async def worst_gap_s(self) -> float:
        self.stop.set()
        await asyncio.wait_for(self.task, 30)
        return max(b - a for a, b in zip(self.times, self.times[1:], strict=False))


# -- 1. an observer stays an observer ---------------------------------------------------------
async def test_an_observer_api_socket_cannot_take_control_with_the_right_token() -> None:
    async with serve() as (app, _, port):
        async with wsc.connect(f"ws://127.0.0.1:{port}/api?mode=observe") as observer:
            auth = await call(observer, "server.auth", 1, token=TOKEN)
            hold = await call(observer, "machine.hold", 2)
            sent = await call(observer, "gcode.send", 3, lines="G0 X5")
            info = await call(observer, "server.info", 4)
        url = f"ws://127.0.0.1:{port}/api?mode=observe&token={TOKEN}"
        async with wsc.connect(url) as with_token:
            jog = await call(with_token, "machine.jog", 1, x=5, feed_mm_min=600)
        assert app.kernel.machine.planner.position_mm == (0.0, 0.0, 0.0)
    assert auth["error"]["code"] == 46 and hold["error"]["code"] == 46
    assert sent["result"]["results"][0]["reply"] == "error:46"
    assert info["result"]["can_control"] is False and jog["error"]["code"] == 46


# -- 2. DNS rebinding ---------------------------------------------------------------------------
async def test_a_rebinding_host_is_refused_on_every_route_and_local_names_are_served() -> None:
    async with serve() as (_, _, port):
        evil = f"Host: evil.example:{port}\r\n"
        refused = [await http_status(port, f"GET {path} HTTP/1.1\r\n{evil}")
                   for path in ("/", "/index.html", "/js/api.js", "/ws", "/api", "/missing")]
        upload = await http_status(port, f"POST /upload?name=a.gcode&token={TOKEN} HTTP/1.1\r\n"
                                         f"{evil}Content-Length: 0\r\n")
        local = [await http_status(port, f"GET / HTTP/1.1\r\nHost: {host}\r\n")
                 for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}",
                              f"ui.localhost:{port}", "LOCALHOST.")]
        statuses = []
        async with aiohttp.ClientSession() as session:
            for path in ("/ws", f"/api?token={TOKEN}"):
                headers = {"Host": f"evil.example:{port}", "Origin": f"http://evil.example:{port}"}
                with pytest.raises(aiohttp.WSServerHandshakeError) as error:
                    await session.ws_connect(f"http://127.0.0.1:{port}{path}", headers=headers)
                statuses.append(error.value.status)
    assert refused == [403] * 6 and upload == 403 and statuses == [403, 403]
    assert local == [200] * 5


async def test_allowed_hosts_replace_the_local_names_and_an_origin_must_be_allowed() -> None:
    async with serve(allowed_hosts=["cnc.lan", "*.shop.lan"]) as (_, _, port):
        named = [await http_status(port, f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\n")
                 for host in ("cnc.lan", "laser.shop.lan", "localhost", "shop.lan")]
        async with aiohttp.ClientSession() as session:
            same = {"Host": f"cnc.lan:{port}", "Origin": f"http://cnc.lan:{port}"}
            async with session.ws_connect(f"http://127.0.0.1:{port}/ws", headers=same) as ws:
                await ws.send_str("?")
                report = await asyncio.wait_for(ws.receive_str(), 10)
            other = {"Host": f"cnc.lan:{port}", "Origin": f"http://evil.example:{port}"}
            with pytest.raises(aiohttp.WSServerHandshakeError) as foreign:
                await session.ws_connect(f"http://127.0.0.1:{port}/api", headers=other)
    async with serve(allowed_hosts=["*"]) as (_, _, port):
        anything = await http_status(port, f"GET / HTTP/1.1\r\nHost: evil.example:{port}\r\n")
    assert named == [200, 200, 403, 403] and report.strip()
    assert foreign.value.status == 403 and anything == 200


# -- 3. one frame must not freeze the loop or grow memory ---------------------------------------
async def test_a_4_mib_line_socket_frame_is_closed_1009_while_tcp_status_keeps_answering() -> None:
    async with serve() as (_, tcp_port, port):
        poller = StatusPoller(tcp_port)
        await poller.started()
        async with wsc.connect(f"ws://127.0.0.1:{port}/ws", compression=None,
                                      max_size=None) as socket:
            with contextlib.suppress(wsc.ConnectionClosed):
                await socket.send("\n" * (4 * MIB - 1024))
            code = await close_code(socket)
        await asyncio.sleep(0.3)
        worst_gap_s = await poller.worst_gap_s()
    assert code == 1009
    assert worst_gap_s < 2.0  # the unbounded frame froze the loop ~7 s


async def test_a_deflate_bomb_is_bounded_by_its_decompressed_size() -> None:
    deflate = zlib.compressobj(wbits=-15)
    payload = deflate.compress(b"\n" * (4 * MIB - 1024)) + deflate.flush(zlib.Z_SYNC_FLUSH)
    frame = client_frame(payload.removesuffix(b"\x00\x00\xff\xff"), compressed=True)
    async with serve() as (_, _, port):
        reader, writer, head = await ws_handshake(
            port, "/ws", b"Sec-WebSocket-Extensions: permessage-deflate\r\n")
        writer.write(frame)
        opcodes, payloads = [], []
        while not opcodes or opcodes[-1] != 0x8:
            opcode, data = await server_frame(reader)
            opcodes.append(opcode)
            payloads.append(data)
        writer.close()
    assert b"101" in head.split(b"\r\n")[0] and b"permessage-deflate" in head
    assert len(frame) < 8192  # a few KiB on the wire: the limit must apply after inflating
    assert opcodes == [0x1, 0x8]  # the banner, then the close: no line was ever answered
    assert int.from_bytes(payloads[-1][:2], "big") == 1009


async def test_a_large_allowed_line_socket_message_is_fed_a_slice_per_loop_turn() -> None:
    async with serve(ws_max_message_bytes=4 * MIB) as (_, tcp_port, port):
        poller = StatusPoller(tcp_port)
        await poller.started()
        socket = await wsc.connect(f"ws://127.0.0.1:{port}/ws", compression=None,
                                          max_size=None)
        await socket.send("\n" * (4 * MIB - 1024))
        for _ in range(20):  # answers flow while the message is still being read
            await asyncio.wait_for(socket.recv(), 10)
        await asyncio.sleep(0.3)
        socket.transport.abort()  # the server drops the rest of the message
        worst_gap_s = await poller.worst_gap_s()
    assert worst_gap_s < 2.0


async def test_api_messages_are_bounded_and_smaller_before_the_token() -> None:
    def padded(size: int) -> str:
        return json.dumps({"jsonrpc": "2.0", "id": 1, "method": "server.info", "pad": "x" * size})

    async with serve() as (_, _, port):
        async with wsc.connect(f"ws://127.0.0.1:{port}/api", max_size=None) as anonymous:
            small = await call(anonymous, "server.info")
            await anonymous.send(padded(100_000))
            anonymous_code = await close_code(anonymous)
        url = f"ws://127.0.0.1:{port}/api?token={TOKEN}"
        async with wsc.connect(url, max_size=None, compression=None) as operator:
            await operator.send(padded(100_000))
            allowed = await answer(operator)
            await operator.send(padded(2 * MIB))
            operator_code = await close_code(operator)
    assert "result" in small and anonymous_code == 1009
    assert "result" in allowed and operator_code == 1009


async def test_deep_nesting_and_non_finite_numbers_get_errors_and_the_connection_survives() -> None:
    frames = [
        "[" * 10_000,
        '{"jsonrpc": "2.0", "id": 2, "method": "server.info", "params": {"a": '
        + "[" * 40 + "]" * 40 + "}}",
        '{"jsonrpc": "2.0", "id": NaN, "method": "server.info"}',
        '{"jsonrpc": "2.0", "id": Infinity, "method": "server.info"}',
        '{"jsonrpc": "2.0", "id": -Infinity, "method": "server.info"}',
        '{"jsonrpc": "2.0", "id": 1e400, "method": "server.info"}',
        '{"jsonrpc": "2.0", "id": true, "method": "server.info"}',
    ]
    async with (
        serve() as (_, _, port),
        wsc.connect(f"ws://127.0.0.1:{port}/api") as socket,
    ):
        errors = []
        for frame in frames:
            await socket.send(frame)
            errors.append(await answer(socket))
        quoted = await call(socket, "server.info", 9, note="[" * 5000)
        after = await call(socket, "server.info", 10)
    assert [error["error"]["code"] for error in errors[:2]] == [-32600, -32600]
    assert all(error["error"]["code"] in (-32600, -32700) for error in errors)
    assert all(error["id"] is None for error in errors)
    assert quoted["error"]["code"] == -32602  # brackets inside a string are not nesting
    assert after["result"]["name"] == "motiond"


async def test_tokens_that_are_not_ascii_get_clean_refusals() -> None:
    async with serve() as (_, _, port):
        async with wsc.connect(f"ws://127.0.0.1:{port}/api?token=%C3%A9") as api:
            info = await call(api, "server.info", 1)
            accented = await call(api, "server.auth", 2, token="é")
            await api.send('{"jsonrpc": "2.0", "id": 3, "method": "server.auth", '
                           '"params": {"token": "\\ud800"}}')
            surrogate = await answer(api)
        uploads = [await http_status(port, f"POST /upload?name=a.gcode HTTP/1.1\r\n"
                                           f"Host: 127.0.0.1:{port}\r\nX-Motiond-Token: {token}"
                                           "\r\nContent-Length: 0\r\n")
                   for token in ("é", "\udcff")]
        reader, writer, head = await ws_handshake(port, "/ws", b"X-Motiond-Token: \xff\xfe\r\n")
        writer.write(client_frame(b"G0 X1\n"))
        replies = [await server_frame(reader) for _ in range(2)]
        writer.close()
    assert info["result"]["can_control"] is False
    assert accented["error"]["code"] == 46 and surrogate["error"]["code"] == 46
    assert uploads == [401, 401]
    assert b"101" in head.split(b"\r\n")[0] and replies[1] == (0x1, b"error:46\r\n")


# -- 4. lock-out and exhaustion -----------------------------------------------------------------
async def test_sockets_without_the_token_cannot_lock_the_operator_out() -> None:
    async with serve() as (_, _, port), contextlib.AsyncExitStack() as stack:
        refused = 0
        for _ in range(32):  # what used to fill every slot
            try:
                await stack.enter_async_context(wsc.connect(f"ws://127.0.0.1:{port}/api"))
            except wsc.InvalidStatus as exc:
                assert exc.response.status_code == 503
                refused += 1
        url = f"ws://127.0.0.1:{port}/api?token={TOKEN}"
        async with wsc.connect(url) as operator:
            info = await call(operator, "server.info")
    assert refused == 32 - 8 and info["result"]["can_control"] is True


async def test_idle_sockets_without_the_token_are_closed_and_the_operators_stay() -> None:
    async with (
        serve(idle_timeout_s=0.5) as (_, _, port),
        wsc.connect(f"ws://127.0.0.1:{port}/api") as idle_api,
        wsc.connect(f"ws://127.0.0.1:{port}/ws") as idle_line,
        wsc.connect(f"ws://127.0.0.1:{port}/api") as chatty,
        wsc.connect(f"ws://127.0.0.1:{port}/api?token={TOKEN}") as operator,
        wsc.connect(f"ws://127.0.0.1:{port}/api") as logged_in,
    ):
        assert "result" in await call(logged_in, "server.auth", token=TOKEN)
        for _ in range(15):  # garbage is not a request: it does not keep a socket open
            with contextlib.suppress(wsc.ConnectionClosed):
                await chatty.send("not json")
            await asyncio.sleep(0.1)
        codes = [await close_code(s) for s in (idle_api, idle_line, chatty)]
        still = [await call(s, "server.info") for s in (operator, logged_in)]
    assert codes == [1008, 1008, 1008]
    assert [answer["result"]["can_control"] for answer in still] == [True, True]


async def test_a_half_sent_request_is_closed_after_the_request_timeout() -> None:
    async with (
        serve(request_timeout_s=0.5) as (_, _, port),
        wsc.connect(f"ws://127.0.0.1:{port}/api?token={TOKEN}") as operator,
    ):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(f"GET /api HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: webs".encode())
        closed = await asyncio.wait_for(reader.read(), 10)
        writer.close()
        await asyncio.sleep(1.0)  # an open WebSocket is not a request being sent
        info = await call(operator, "server.info")
    assert closed == b"" and info["result"]["can_control"] is True


ACCEPT_STARVED = r"""
import asyncio, os, resource, sys
import logging
from server.api.server import http_with_api
from server.app import App
from tests.conftest import make_config

async def main() -> None:
    logging.basicConfig(level=logging.INFO)
    app = App(make_config(), transports=[http_with_api])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    highest_fd = max(int(fd) for fd in os.listdir("/proc/self/fd"))
    resource.setrlimit(resource.RLIMIT_NOFILE,
                       (highest_fd + 4, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
    print(app.transports[0].port, flush=True)
    await asyncio.sleep(float(sys.argv[1]))
    app.request_stop()
    await task

asyncio.run(main())
"""


async def test_running_out_of_descriptors_is_logged_once_per_burst_not_once_per_attempt() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-c", ACCEPT_STARVED, "3.6", cwd=REPO, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert process.stdout is not None
    port = int(await asyncio.wait_for(process.stdout.readline(), 60))
    clients = [await asyncio.open_connection("127.0.0.1", port) for _ in range(20)]
    _, stderr = await asyncio.wait_for(process.communicate(), 60)
    for _, writer in clients:
        writer.close()
    log = stderr.decode()
    assert process.returncode == 0, log
    assert log.count("Too many open files") == 1, log  # asyncio retries (and logged) each 1 s
