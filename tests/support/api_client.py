"""The JSON API from a test's side: a served App on a free HTTP port and a JSON-RPC client on a
real WebSocket connection (aiohttp's client, :mod:`tests.support.websocket_client`)."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from server.api.server import http_with_api
from server.app import App
from server.config import Config
from server.transports.websocket import HttpTransport
from tests.conftest import make_config
from tests.support import websocket_client as wsc
from tests.support.helpers import running


class RpcClient:
    """A JSON-RPC client on a WebSocket connection; notifications are kept in order."""

    def __init__(self, connection: wsc.ClientConnection) -> None:
        self.connection = connection
        self.notifications: list[dict[str, Any]] = []
        self.arrived = asyncio.Event()
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for frame in self.connection:
            message = json.loads(frame)
            future = self._waiting.pop(message.get("id"), None) if "id" in message else None
            if future is not None:
                future.set_result(message)
            else:
                self.notifications.append(message)
                self.arrived.set()

    async def request(self, method: str, **params: Any) -> dict[str, Any]:
        """The whole response message (``result`` or ``error``)."""
        request_id = next(self._ids)
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[request_id] = future
        await self.connection.send(
            json.dumps({"jsonrpc": "2.0", "id": request_id, "method": method, "params": params})
        )
        return await asyncio.wait_for(future, 10)

    async def call(self, method: str, **params: Any) -> Any:
        """The result; fails the test on an error response."""
        response = await self.request(method, **params)
        assert "error" not in response, response
        return response["result"]

    async def error(self, method: str, **params: Any) -> dict[str, Any]:
        response = await self.request(method, **params)
        assert "error" in response, response
        return response["error"]

    async def wait_for(
        self, method: str, predicate: Any = lambda params: True, timeout_s: float = 10.0
    ) -> dict[str, Any]:
        """The first notification (already seen or coming) matching ``predicate``."""
        async with asyncio.timeout(timeout_s):
            seen = 0
            while True:
                for message in self.notifications[seen:]:
                    if message["method"] == method and predicate(message["params"]):
                        return message["params"]
                seen = len(self.notifications)
                self.arrived.clear()
                await self.arrived.wait()

    async def close(self) -> None:
        await self.connection.close()
        self._reader.cancel()
        with contextlib.suppress(asyncio.CancelledError, wsc.ConnectionClosed):
            await self._reader


def api_config(tmp_path: Path, **extra: Any) -> Config:
    return make_config({"jobs": {"data_dir": str(tmp_path)}, **extra})


def http_of(app: App) -> HttpTransport:
    return next(t for t in app.transports if isinstance(t, HttpTransport))


@contextlib.asynccontextmanager
async def serving(config: Config, clock: Any = None) -> AsyncIterator[tuple[App, str]]:
    """A running App with HTTP on a free port; yields it and ``http://127.0.0.1:PORT``."""
    async with running(config, clock, transports=[http_with_api]) as app:
        yield app, f"127.0.0.1:{http_of(app).port}"


@contextlib.asynccontextmanager
async def client(address: str, path: str = "/api", **options: Any) -> AsyncIterator[RpcClient]:
    connection = await wsc.connect(f"ws://{address}{path}", **options)
    rpc = RpcClient(connection)
    try:
        yield rpc
    finally:
        await rpc.close()
