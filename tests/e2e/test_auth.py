"""Optional authentication on the line protocol: $AUTH=token, read-only or no session."""

from __future__ import annotations

import asyncio
import json

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import VirtualClock
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc

TOKEN = "s3cret-token"


async def exchange(port: int, data: bytes, replies: int) -> list[str]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(data)
    lines: list[str] = []
    def answered() -> int:
        return len([line for line in lines if line == "ok" or line.startswith(("error", "<"))])

    while answered() < replies:
        lines.append((await asyncio.wait_for(reader.readline(), 5)).decode().strip())
    writer.close()
    return [line for line in lines if line and not line.startswith("Grbl")]


async def serve(policy: str) -> App:
    config = make_config(protocol={"token": TOKEN, "unauthenticated": policy})
    app = App(config, clock=VirtualClock(), transports=[TcpTransport, http_with_api])
    app.task = asyncio.create_task(app.run())  # type: ignore[attr-defined]
    await app.ready.wait()
    return app


async def stop(app: App) -> None:
    app.request_stop()
    await app.task  # type: ignore[attr-defined]


async def test_without_the_token_a_connection_may_watch_but_not_move() -> None:
    app = await serve("read-only")
    port = app.transports[0].port  # type: ignore[attr-defined]
    lines = await exchange(port, b"G0 X10\n$G\n?", 3)
    replies = [line for line in lines if not line.startswith("<")]
    assert replies[0] == "error:46"
    assert replies[1].startswith("[GC:") and replies[2] == "ok"
    assert any(line.startswith("<Idle|") for line in lines)
    assert app.kernel.machine.planner.position_mm == (0.0, 0.0, 0.0)
    await stop(app)


async def test_auth_with_the_right_token_unlocks_control_and_a_wrong_one_does_not() -> None:
    app = await serve("none")
    port = app.transports[0].port  # type: ignore[attr-defined]
    assert await exchange(port, b"$G\n$AUTH=wrong\nG0 X1\n", 3) == [
        "error:46", "error:46", "error:46"]
    assert await exchange(port, f"$AUTH={TOKEN}\nG0 X1\n".encode(), 2) == ["ok", "ok"]
    await stop(app)


async def test_websocket_lines_take_the_token_from_the_query() -> None:
    app = await serve("none")
    http_port = app.transports[1].port  # type: ignore[attr-defined]
    async with wsc.connect(f"ws://127.0.0.1:{http_port}/ws?token={TOKEN}") as socket:
        await socket.send("G0 X2\n")
        replies = []
        while "ok\r\n" not in replies:
            replies.append(await asyncio.wait_for(socket.recv(), 5))
    async with wsc.connect(f"ws://127.0.0.1:{http_port}/ws") as socket:
        await socket.send("G0 X3\n")
        replies = []
        while not any(r.startswith("error") for r in replies):
            replies.append(await asyncio.wait_for(socket.recv(), 5))
        assert "error:46\r\n" in replies
    await stop(app)


async def test_a_page_on_another_site_cannot_open_the_line_socket() -> None:
    app = await serve("read-only")
    http_port = app.transports[1].port  # type: ignore[attr-defined]
    url = f"ws://127.0.0.1:{http_port}/ws"
    try:
        await wsc.connect(url, origin="http://evil.example")  # type: ignore[arg-type]
        raise AssertionError("a foreign origin was let in")
    except wsc.InvalidStatus as exc:
        assert exc.response.status_code == 403
    same_site = f"http://127.0.0.1:{http_port}"
    async with wsc.connect(url, origin=same_site) as socket:  # type: ignore[arg-type]
        await socket.send("?")
        assert (await asyncio.wait_for(socket.recv(), 5)).strip()
    await stop(app)


async def test_websocket_connections_beyond_the_limit_and_request_floods_get_clear_errors() -> None:
    config = make_config(http={"max_connections": 2, "max_requests_per_s": 20})
    app = App(config, clock=VirtualClock(), transports=[http_with_api])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    port = app.transports[0].port  # type: ignore[attr-defined]
    line_socket = wsc.connect(f"ws://127.0.0.1:{port}/ws")
    async with line_socket, wsc.connect(f"ws://127.0.0.1:{port}/api") as api:
        try:
            await wsc.connect(f"ws://127.0.0.1:{port}/api")
            raise AssertionError("a third connection was let in")
        except wsc.InvalidStatus as exc:
            assert exc.response.status_code == 503
        for request_id in range(60):
            await api.send(json.dumps({"jsonrpc": "2.0", "id": request_id,
                                       "method": "server.info"}))
        answers = [json.loads(await asyncio.wait_for(api.recv(), 5)) for _ in range(60)]
        limited = [a for a in answers if a.get("error", {}).get("code") == -32001]
        assert 20 <= len(answers) - len(limited) <= 25 and len(limited) >= 35
    app.request_stop()
    await task


async def test_observer_connections_watch_but_never_control_even_without_a_token() -> None:
    app = App(make_config(), clock=VirtualClock(), transports=[http_with_api])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    port = app.transports[0].port  # type: ignore[attr-defined]
    async with wsc.connect(f"ws://127.0.0.1:{port}/ws?mode=observe") as socket:
        await socket.send("G0 X5\n?")
        replies = [await asyncio.wait_for(socket.recv(), 5) for _ in range(3)]
        assert "error:46\r\n" in replies and any(r.startswith("<Idle") for r in replies)
    async with wsc.connect(f"ws://127.0.0.1:{port}/api?mode=observe") as api:
        await api.send(json.dumps({"jsonrpc": "2.0", "id": 1, "method": "machine.hold"}))
        assert json.loads(await asyncio.wait_for(api.recv(), 5))["error"]["code"] == 46
        await api.send(json.dumps({"jsonrpc": "2.0", "id": 2, "method": "machine.status"}))
        assert "result" in json.loads(await asyncio.wait_for(api.recv(), 5))
    assert app.kernel.machine.planner.position_mm == (0.0, 0.0, 0.0)
    app.request_stop()
    await task
