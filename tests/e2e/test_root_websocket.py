"""A WebSocket upgrade on ``/`` is the line socket, as on ``/ws`` (FluidNC and the ESP32 WebUIs
serve theirs on the root, and MeerK40t connects to ``ws://host:port/``); a plain ``GET /`` is
still the web page. The same access rules apply on both paths."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import aiohttp
import pytest

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import VirtualClock
from tests.conftest import make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running

TOKEN = "root-token"


@pytest.fixture
async def port() -> AsyncIterator[int]:
    config = make_config(protocol={"token": TOKEN, "unauthenticated": "read-only"})
    async with running(config, VirtualClock(), [http_with_api]) as app:
        yield _port(app)


def _port(app: App) -> int:
    return app.transports[0].port  # type: ignore[attr-defined, no-any-return]


async def replies_until(socket: wsc.ClientConnection, last: str) -> list[str]:
    replies: list[str] = []
    while not replies or not replies[-1].startswith(last):
        replies.append(str(await asyncio.wait_for(socket.recv(), 5)).strip())
    return replies


async def test_a_websocket_on_the_root_speaks_the_line_protocol(port: int) -> None:
    async with wsc.connect(f"ws://127.0.0.1:{port}/?token={TOKEN}") as socket:
        assert (await replies_until(socket, "Grbl"))[-1] == "Grbl 1.1h ['$' for help]"
        await socket.send("G0 X2\n")
        assert await replies_until(socket, "ok") == ["ok"]
        await socket.send("?")
        assert (await replies_until(socket, "<")).pop().startswith("<")


async def test_the_root_socket_keeps_the_access_rules_of_ws(port: int) -> None:
    async with wsc.connect(f"ws://127.0.0.1:{port}/") as socket:  # no token: read-only
        await socket.send("G0 X3\n")
        assert (await replies_until(socket, "error"))[-1] == "error:46"
    with pytest.raises(wsc.InvalidStatus) as refused:
        await wsc.connect(f"ws://127.0.0.1:{port}/", origin="http://evil.example")
    assert refused.value.response.status_code == 403


async def test_a_plain_get_of_the_root_is_still_the_web_page(port: int) -> None:
    async with aiohttp.ClientSession() as session, session.get(
            f"http://127.0.0.1:{port}/") as response:
        assert response.status == 200
        assert "<html" in (await response.text()).lower()
