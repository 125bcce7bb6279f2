"""Hostile input and churn against a live server: nothing crashes, nothing is lost, memory and
tasks stay bounded. Sizes grow with MOTIOND_SOAK_LINES."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import os
import random
import socket
import tracemalloc

import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import VirtualClock
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc

SOAK_LINES = int(os.environ.get("MOTIOND_SOAK_LINES", "5000"))  # CI's bounded size


async def start_app() -> tuple[App, asyncio.Task[None], int, int]:
    app = App(make_config(tcp={"max_connections": 64}), clock=VirtualClock(),
              transports=[TcpTransport, http_with_api])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    tcp, http = app.transports
    return app, task, tcp.port, http.port  # type: ignore[attr-defined]


async def read_until(reader: asyncio.StreamReader, marker: bytes, timeout_s: float = 10) -> bytes:
    data = b""
    while marker not in data:
        chunk = await asyncio.wait_for(reader.read(65536), timeout_s)
        if not chunk:
            break
        data += chunk
    return data


def garbage(rng: random.Random) -> bytes:
    kind = rng.randrange(6)
    if kind == 0:
        return rng.randbytes(rng.randrange(1, 600))
    if kind == 1:
        return b"G1 X1" + bytes([rng.choice([0x3F, 0x91, 0x93, 0x85])]) + b"0.5 F100\n"
    if kind == 2:
        return b"\x00" * rng.randrange(1, 50) + b"\n"
    if kind == 3:
        return "G0 X\u00e9\udcff".encode("utf-8", "surrogatepass") + b"\n"
    if kind == 4:
        return b"G1 X" + b"9" * rng.randrange(300, 3000) + b"\n"
    return b"(unclosed comment G0 X5\n$$\n"


async def test_random_bytes_over_a_live_port_never_crash_and_the_next_lines_work() -> None:
    app, task, port, _ = await start_app()
    rng = random.Random(1234)
    for _ in range(40):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        for _ in range(rng.randrange(1, 10)):
            writer.write(garbage(rng))
        if rng.random() < 0.3:
            writer.write_eof()  # half-closed
        await writer.drain()
        await asyncio.sleep(0)
        writer.transport.abort() if rng.random() < 0.5 else writer.close()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"\x18")
    await read_until(reader, b"Grbl 1.1h")
    writer.write(b"$X\nG90 G0 X7 Y3\n$G\n")
    reply = await read_until(reader, b"[GC:")
    assert b"ok" in reply
    await app.kernel.machine.wait_idle()
    assert app.kernel.machine.backend.steps[:2] == [560, 240]
    writer.close()
    app.request_stop()
    await task


async def test_a_huge_line_without_newline_keeps_memory_bounded_and_is_answered_once() -> None:
    app, task, port, _ = await start_app()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await read_until(reader, b"Grbl 1.1h")
    tracemalloc.start()
    baseline = tracemalloc.get_traced_memory()[0]
    chunk = b"G1X" + b"1" * 65533
    for _ in range(80):  # 5 MiB without a newline
        writer.write(chunk)
        await writer.drain()
    writer.write(b"\nG0 X2\n")
    reply = await read_until(reader, b"ok")
    grown = tracemalloc.get_traced_memory()[1] - baseline
    tracemalloc.stop()
    assert reply.count(b"error:11") == 1 and reply.count(b"ok") == 1
    assert grown < 2 * 1024 * 1024, f"{grown} bytes held while receiving a 5 MiB line"
    writer.close()
    app.request_stop()
    await task


async def churn(port: int, http_port: int, rng: random.Random, stop: asyncio.Event) -> int:
    """Clients that connect, poll, subscribe and vanish at random until told to stop."""
    visits = 0
    while not stop.is_set():
        visits += 1
        if rng.random() < 0.3:
            with contextlib.suppress(OSError, wsc.WebSocketException, TimeoutError):
                async with wsc.connect(f"ws://127.0.0.1:{http_port}/api") as api:
                    await api.send(json.dumps({"jsonrpc": "2.0", "id": 1,
                                               "method": "machine.subscribe", "params": {}}))
                    await asyncio.wait_for(api.recv(), 5)
            continue
        with contextlib.suppress(OSError, TimeoutError, ConnectionError):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            for _ in range(rng.randrange(1, 5)):
                writer.write(b"?")
                await asyncio.sleep(0.001)
            if rng.random() < 0.5:
                writer.transport.abort()
            else:
                writer.close()
        await asyncio.sleep(0.002)
    return visits


@pytest.mark.soak
async def test_soak_streaming_with_clients_churning_loses_nothing_and_leaks_nothing() -> None:
    app, task, port, http_port = await start_app()
    gc.collect()
    tasks_before = len(asyncio.all_tasks())
    objects_before = len(gc.get_objects())
    rng = random.Random(99)
    stop = asyncio.Event()
    churners = [asyncio.create_task(churn(port, http_port, random.Random(i), stop))
                for i in range(3)]
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await read_until(reader, b"Grbl 1.1h")
    lines = random_walk(rng, SOAK_LINES)
    replies = await character_counted(reader, writer, lines)
    stop.set()
    visits = sum(await asyncio.gather(*churners))
    await app.kernel.machine.wait_idle()
    assert replies == ["ok"] * SOAK_LINES
    x, y = (float(word[1:]) for word in lines[-1].split()[1:3])
    assert app.kernel.machine.backend.steps[:2] == [round(x * 80), round(y * 80)]
    writer.close()
    await asyncio.sleep(0.05)
    gc.collect()
    assert visits > 20
    assert len(asyncio.all_tasks()) <= tasks_before + 1, "no connection task leaked"
    grown = len(gc.get_objects()) - objects_before
    # 150 seen: a leak of one object in two lines would show
    assert grown < SOAK_LINES // 2, f"{grown} objects more after {SOAK_LINES} lines"
    app.request_stop()
    await task


def random_walk(rng: random.Random, count: int) -> list[bytes]:
    """Short moves (under a millimetre) wandering inside the travel: lots of lines, little time."""
    x, y, lines = 200.0, 150.0, []
    for _ in range(count):
        x = min(390.0, max(10.0, x + rng.uniform(-0.8, 0.8)))
        y = min(290.0, max(10.0, y + rng.uniform(-0.8, 0.8)))
        lines.append(f"G1 X{x:.3f} Y{y:.3f} F6000".encode())
    return lines


async def character_counted(reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                            lines: list[bytes], window: int = 128) -> list[str]:
    """Grbl character counting: keep at most ``window`` unacknowledged bytes in flight."""
    replies: list[str] = []
    in_flight: list[int] = []
    buffer = b""
    index = 0
    while len(replies) < len(lines):
        while index < len(lines) and sum(in_flight) + len(lines[index]) + 1 <= window:
            writer.write(lines[index] + b"\n")
            in_flight.append(len(lines[index]) + 1)
            index += 1
        buffer += await asyncio.wait_for(reader.read(65536), 30)
        *complete, buffer = buffer.split(b"\r\n")
        for line in complete:
            text = line.decode()
            if text == "ok" or text.startswith("error"):
                replies.append(text)
                in_flight.pop(0)
    return replies


def test_the_tcp_port_refuses_connections_beyond_the_limit() -> None:
    async def scenario() -> None:
        app = App(make_config(tcp={"max_connections": 2}), clock=VirtualClock(),
                  transports=[TcpTransport])
        task = asyncio.create_task(app.run())
        await app.ready.wait()
        port = app.transports[0].port  # type: ignore[attr-defined]
        held = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
        for reader, _ in held:
            await read_until(reader, b"Grbl")
        reader, _ = await asyncio.open_connection("127.0.0.1", port)
        assert b"too many connections" in await read_until(reader, b"connections")
        for _, writer in held:
            writer.close()
        app.request_stop()
        await task

    asyncio.run(scenario())
    with contextlib.suppress(OSError):
        socket.socket().close()
