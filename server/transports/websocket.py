"""The HTTP port: the web UI's static files, the line protocol over WebSocket at ``/ws``.

``/ws`` speaks exactly what TCP speaks: one or more lines per text frame in (realtime bytes
also UTF-8 encoded), one text frame per reply or pushed line out. Other routes (the JSON API,
uploads) are added by :func:`add_routes` hooks.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from aiohttp import WSMsgType, web

from server.session import Session, login_guard

if TYPE_CHECKING:
    from server.kernel import Kernel

log = logging.getLogger("motiond.http")
RouteHook = Callable[["HttpTransport", web.Application], None]


def origin_allowed(request: web.Request, allowed_origins: list[str]) -> bool:
    """Whether a request may act on the machine: no Origin (not a browser), the page's own
    origin, or one listed in ``[http] allowed_origins`` ("*" allows any). A page on another
    site must not drive the machine through the user's browser."""
    origin = request.headers.get("Origin")
    if origin is None or origin in allowed_origins or "*" in allowed_origins:
        return True
    return urlsplit(origin).netloc.lower() == request.host.lower()


def _browsable(host: str) -> str:
    """An address a browser on this machine can open for a bind address."""
    return "127.0.0.1" if host in ("0.0.0.0", "", "::") else host


def web_root() -> Path:
    """The folder of the browser UI (installed as the ``web`` package)."""
    return Path(str(resources.files("web")))


class HttpTransport:
    """Serves ``[http] host:port``."""

    name = "http"
    route_hooks: list[RouteHook] = []

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.config = kernel.config.core.http
        self.port = self.config.port
        self.app = web.Application(client_max_size=kernel.config.core.jobs.max_upload_bytes)
        self.app.router.add_get("/ws", self._line_socket)
        for hook in self.route_hooks:
            hook(self, self.app)
        self.app.router.add_get("/", self._index)
        self.app.router.add_static("/", web_root(), show_index=False)
        self._runner: web.AppRunner | None = None
        self._sockets: set[web.WebSocketResponse] = set()
        self.open_sockets = 0  # /ws and /api together
        self._ids = itertools.count(1)
        self._guard = login_guard(kernel)

    async def start(self) -> None:
        self._runner = web.AppRunner(
            self.app, access_log=None, handle_signals=False, shutdown_timeout=0.5
        )
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.config.host, self.config.port)
        await site.start()
        server = site._server  # noqa: SLF001 - aiohttp exposes the bound port only here
        if server is not None and server.sockets:  # type: ignore[attr-defined]
            self.port = server.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        log.info("HTTP/WebSocket listening on %s:%d — web UI at http://%s:%d/",
                 self.config.host, self.port, _browsable(self.config.host), self.port)

    async def close(self) -> None:
        for socket in list(self._sockets):
            with contextlib.suppress(Exception):
                await socket.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        self._guard.close()

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(web_root() / "index.html")

    def admit(self, request: web.Request) -> None:
        """Refuse a WebSocket from a foreign origin (403) or beyond ``max_connections`` (503)."""
        if not origin_allowed(request, self.config.allowed_origins):
            log.warning("refused %s from origin %s", request.path, request.headers.get("Origin"))
            raise web.HTTPForbidden(text="origin not allowed")
        if self.open_sockets >= self.config.max_connections:
            log.warning("refused %s: %d connections open", request.path, self.open_sockets)
            raise web.HTTPServiceUnavailable(text="too many connections")

    async def _line_socket(self, request: web.Request) -> web.WebSocketResponse:
        self.admit(request)
        socket = web.WebSocketResponse(heartbeat=20)
        await socket.prepare(request)
        self._sockets.add(socket)
        self.open_sockets += 1
        token = request.query.get("token") or request.headers.get("X-Motiond-Token")
        observer = request.query.get("mode") == "observe"
        session = Session(self.kernel, f"ws-{next(self._ids)}", websocket=True, token=token,
                          observer=observer, peer=request.remote or "?", guard=self._guard)
        transport = request.transport
        if transport is not None:
            session.outbox.on_overflow = transport.abort
        session.start()
        writer = asyncio.create_task(_write_lines(session, socket))
        try:
            async for message in socket:
                if message.type is WSMsgType.TEXT:
                    session.receive_text(message.data)
                elif message.type is WSMsgType.BINARY:
                    session.receive_data(message.data)
                await session.wait_room()
                await asyncio.sleep(0)  # one message a turn: a flood must not hold the loop
        finally:
            self._sockets.discard(socket)
            self.open_sockets -= 1
            await session.close()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await writer
        return socket


async def _write_lines(session: Session, socket: web.WebSocketResponse) -> None:
    while True:
        data = await session.outbox.get()
        if data is None:
            if not session.outbox.overflowed:
                await socket.close()  # the session ended (it said why): hang up
            return
        for line in data.decode("utf-8", "replace").splitlines(keepends=True):
            if line.strip():
                await socket.send_str(line)
