"""Hostile uploads on the HTTP port: compressed bodies are refused without being inflated, and
a refused request's body is never read: the connection closes. Raw sockets, so what the
server reads and when it hangs up is seen as it is."""

from __future__ import annotations

import asyncio
import time
import zlib
from pathlib import Path

from server.api.server import http_with_api
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.e2e.test_hostile_lines import http_port, tcp_port
from tests.support.helpers import running

TOKEN = "s3cret-token"
WORST_STALL_S = 0.05  # inflating it on the loop took far longer


def gzip_bomb(inflated_mib: int) -> bytes:
    """A gzip body of a few tens of KiB that inflates to ``inflated_mib`` MiB of newlines."""
    packer = zlib.compressobj(9, zlib.DEFLATED, 31)
    mebibyte = b"\n" * (1 << 20)
    return b"".join(packer.compress(mebibyte) for _ in range(inflated_mib)) + packer.flush()


BOMB = gzip_bomb(256)


def post(port: int, path: str, body: bytes, *headers: str) -> bytes:
    head = "\r\n".join([f"POST {path} HTTP/1.1", f"Host: 127.0.0.1:{port}",
                        f"Content-Length: {len(body)}", *headers, "", ""])
    return head.encode() + body


async def exchange(port: int, request: bytes) -> tuple[bytes, float]:
    """Send ``request`` (headers first, then the body in pieces), read until the server hangs
    up; the answer and the seconds that took."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    start_s = time.monotonic()
    head_end = request.index(b"\r\n\r\n") + 4
    writer.write(request[:head_end])
    answer = b""
    try:
        for offset in range(head_end, len(request), 65536):
            writer.write(request[offset:offset + 65536])
            await writer.drain()
    except ConnectionError:
        pass  # the server hung up mid-body: what we want
    async with asyncio.timeout(10):
        while chunk := await reader.read(65536):
            answer += chunk
    writer.close()
    return answer, time.monotonic() - start_s


async def status_round_trip_s(port: int) -> float:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await reader.readuntil(b"help]\r\n")
    start_s = time.monotonic()
    writer.write(b"?")
    await reader.readuntil(b">")
    writer.close()
    return time.monotonic() - start_s


async def test_a_gzip_upload_is_refused_unread_with_or_without_the_token(tmp_path: Path) -> None:
    config = make_config(protocol={"token": TOKEN}, http={"token": TOKEN},
                         jobs={"data_dir": str(tmp_path)})
    async with running(config, transports=[TcpTransport, http_with_api]) as app:
        port = http_port(app)
        app.kernel.loop_monitor.reset()
        answers = []
        for headers in ((f"X-Motiond-Token: {TOKEN}", "Content-Encoding: gzip"),
                        ("Content-Encoding: gzip",), ()):
            answers.append(await exchange(port, post(port, "/upload?name=bomb.nc", BOMB,
                                                     *headers)))
        round_trip_s = await status_round_trip_s(tcp_port(app))
        worst_stall_s = app.kernel.loop_monitor.worst_cpu_stall_s
    (with_token, _), (without_token, _), (plain_without_token, _) = answers
    assert with_token.startswith(b"HTTP/1.1 415"), with_token[:200]
    assert b"Content-Encoding" in with_token
    assert without_token.startswith(b"HTTP/1.1 415"), without_token[:200]
    assert plain_without_token.startswith(b"HTTP/1.1 401"), plain_without_token[:200]
    assert all(b"Connection: close" in answer for answer, _ in answers)
    assert [path.name for path in tmp_path.iterdir()] == [], "nothing stored"
    assert round_trip_s < 1.0
    assert worst_stall_s < WORST_STALL_S, worst_stall_s
