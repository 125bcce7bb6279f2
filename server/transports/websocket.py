"""The HTTP port: the web UI's static files, the line protocol over WebSocket at ``/ws``
(and at ``/`` for a WebSocket upgrade, where FluidNC serves it; a plain ``GET /`` is the page).

``/ws`` speaks exactly what TCP speaks: one or more lines per text frame in (realtime bytes
also UTF-8 encoded), one text frame per reply or pushed line out. Other routes (the JSON API,
uploads) are added by :func:`add_routes` hooks.

Every request must name an allowed host (:mod:`server.transports.access`), or gets 403, static
files included; ``/health`` (Docker's ``HEALTHCHECK``: ``ok``) answers any host. An unknown path
gets a plain-text 404, logged (one line per second at most, with the count of the others).
WebSockets also need an allowed origin and a free slot: those that presented the token and
those that did not are counted apart, and the latter are closed after ``[http]
idle_timeout_s`` without a message. A message is bounded once decompressed
(``ws_max_message_bytes``: close 1009) and fed to the session a slice at a time, so one large
message never holds the loop. A request's headers must arrive within ``request_timeout_s``.
Request bodies are never inflated (``Content-Encoding`` is refused where a body is read) and
never drained after a refusal: the connection is closed instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from aiohttp import WSCloseCode, WSMsgType, web

from server.config import trusted_client
from server.sessions.session import Session, line_token, login_guard
from server.transports.access import (
    ConnectionSlots,
    HostPolicy,
    default_hosts,
    machine_names,
    origin_allowed,
    tokens_equal,
    usable_token,
)
from server.transports.first_request import FirstRequestGuard, GuardedSite

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

log = logging.getLogger("motiond.http")
RouteHook = Callable[["HttpTransport", web.Application], None]
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
HEARTBEAT_S = 20.0
SLICE_CHARS = 1024  # of one /ws message per loop turn (TCP reads 4096 bytes a turn)


class NotFoundLog:
    """Logs requests for unknown paths: one line per ``interval_s``, counting the rest."""

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self._logged_s = -math.inf
        self._unlogged = 0

    def note(self, request: web.Request) -> None:
        now_s = time.monotonic()
        if now_s - self._logged_s < self.interval_s:
            self._unlogged += 1
            return
        others = f" (and {self._unlogged} more since)" if self._unlogged else ""
        log.info("404 %s %r from %s%s", request.method, request.path, request.remote, others)
        self._logged_s, self._unlogged = now_s, 0


def _browsable(host: str) -> str:
    """An address a browser on this machine can open for a bind address."""
    return "127.0.0.1" if host in ("0.0.0.0", "", "::") else host


def web_root() -> Path:
    """The folder of the browser UI (installed as the ``web`` package)."""
    return Path(str(resources.files("web")))


def presented_token(request: web.Request) -> str | None:
    """``?token=`` or the ``X-Motiond-Token`` header, if it is text at all."""
    return usable_token(request.query.get("token") or request.headers.get("X-Motiond-Token"))


class HttpTransport:
    """Serves ``[http] host:port``."""

    name = "http"

    def __init__(self, kernel: Kernel, route_hooks: Sequence[RouteHook] = ()) -> None:
        """``route_hooks`` add routes (the JSON API's ``/api`` and ``/upload``)."""
        self.kernel = kernel
        self.config = kernel.config.core.http
        self.port = self.config.port
        self.hosts = self._host_policy([])
        self.slots = ConnectionSlots(
            self.config.max_connections, self.config.max_unauthenticated_connections
        )
        self.app = web.Application(
            client_max_size=kernel.config.core.jobs.max_upload_bytes, middlewares=[self._guard]
        )
        self.app.router.add_get("/ws", self._line_socket)
        self.app.router.add_get("/health", self._health)
        for hook in route_hooks:
            hook(self, self.app)
        self.app.router.add_get("/", self._index)
        self.app.router.add_static("/", web_root(), show_index=False)
        self._runner: web.AppRunner | None = None
        self._sockets: set[web.WebSocketResponse] = set()
        self._ids = itertools.count(1)
        self._login_guard = login_guard(kernel)
        self._not_found = NotFoundLog()
        self.first_request = FirstRequestGuard(
            self.config.max_pending_requests, self.config.first_request_timeout_s)

    def _host_policy(self, machine_names: list[str]) -> HostPolicy:
        allowed = self.config.allowed_hosts or default_hosts(self.config.host, machine_names)
        return HostPolicy([*allowed, *self.config.also_allowed_hosts])

    async def start(self) -> None:
        if self.config.allowed_hosts is None:
            self.hosts = self._host_policy(await machine_names())
        self._runner = web.AppRunner(
            self.app,
            access_log=None,
            handle_signals=False,
            shutdown_timeout=0.5,
            keepalive_timeout=self.config.request_timeout_s,
            auto_decompress=False,  # never inflate a body on the loop (uploads refuse encodings)
            lingering_time=0,  # a refused request's body is never drained: the connection closes
        )
        await self._runner.setup()
        site = GuardedSite(self._runner, self.config.host, self.config.port, self.first_request)
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
        self._login_guard.close()

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Every route: a ``Host`` this server does not answer to is a rebinding page: 403."""
        self.first_request.arrived(request.protocol)
        host = request.headers.get("Host")
        if not self.hosts.allows(host) and request.path != "/health":
            self.hosts.note_refused(str(host), request.path)
            raise web.HTTPForbidden(text="host not allowed")
        try:
            if not await self._static_file_exists(request):
                raise web.HTTPNotFound()
            return await handler(request)
        except web.HTTPNotFound:
            self._not_found.note(request)
            return web.Response(status=404, text="404: not found\n",
                                headers={"X-Content-Type-Options": "nosniff"})

    async def _static_file_exists(self, request: web.Request) -> bool:
        """False for a web UI path with no file (aiohttp would answer an empty 404 typed
        application/octet-stream, which a browser downloads); the static handler still makes
        every other check (paths that leave the folder are its 404s)."""
        resource = request.match_info.route.resource
        if not isinstance(resource, web.StaticResource):
            return True
        path = web_root() / request.match_info.get("filename", "")
        return await asyncio.to_thread(path.is_file)

    async def _health(self, request: web.Request) -> web.StreamResponse:
        """The server answers: its loop runs (an alarm is the machine's state, not ill health)."""
        return web.Response(text="ok\n", headers={"Cache-Control": "no-store"})

    async def _index(self, request: web.Request) -> web.StreamResponse:
        """The web UI's page; a WebSocket upgrade on ``/`` is ``/ws`` (FluidNC and the ESP32
        WebUIs serve their socket on the root, and senders such as MeerK40t connect there)."""
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return await self._line_socket(request)
        return web.FileResponse(web_root() / "index.html")

    def origin_allowed(self, request: web.Request) -> bool:
        """Same-origin pages on an allowed host, listed origins, non-browser clients."""
        return origin_allowed(
            request.headers.get("Origin"),
            request.headers.get("Host"),
            self.config.allowed_origins,
            self.hosts,
        )

    def trusted(self, request: web.Request) -> bool:
        """The client's address is in ``[protocol] trusted_clients``: no token needed."""
        return trusted_client(request.remote, self.kernel.config.core.protocol.trusted_clients)

    def admit(self, request: web.Request, authenticated: bool) -> None:
        """Refuse a WebSocket from a foreign origin (403), or beyond the connection limit for
        those with (``max_connections``) or without the token (503); else take a slot."""
        if not self.origin_allowed(request):
            log.warning("refused %s from origin %s", request.path, request.headers.get("Origin"))
            raise web.HTTPForbidden(text="origin not allowed")
        if not self.slots.take(authenticated):
            kind = "with" if authenticated else "without"
            log.warning("refused %s: %d connections %s the token open", request.path,
                        self.slots.open[authenticated], kind)
            raise web.HTTPServiceUnavailable(text=f"too many connections {kind} the token")

    def idle_deadline(self, authenticated: bool) -> float | None:
        """When a socket without the token that keeps quiet is closed (None: never)."""
        if authenticated:
            return None
        return asyncio.get_running_loop().time() + self.config.idle_timeout_s

    @contextlib.asynccontextmanager
    async def idle_limit(
        self, socket: web.WebSocketResponse, authenticated: bool
    ) -> AsyncIterator[asyncio.Timeout]:
        """Run a socket's receive loop; close the socket once the deadline passes."""
        idle = asyncio.timeout_at(self.idle_deadline(authenticated))
        try:
            async with idle:
                yield idle
        except TimeoutError:
            if not idle.expired():
                raise
            log.info("closing a socket without the token: idle for %gs",
                     self.config.idle_timeout_s)
            await socket.close(code=WSCloseCode.POLICY_VIOLATION, message=b"idle")

    async def _line_socket(self, request: web.Request) -> web.WebSocketResponse:
        token, expected = presented_token(request), line_token(self.kernel)
        authenticated = expected is None or self.trusted(request) or tokens_equal(token, expected)
        self.admit(request, authenticated)
        socket = web.WebSocketResponse(
            heartbeat=HEARTBEAT_S, max_msg_size=self.config.ws_max_message_bytes
        )
        try:
            await socket.prepare(request)
            self._sockets.add(socket)
            await self._serve_lines(request, socket, token, authenticated)
        finally:
            self._sockets.discard(socket)
            self.slots.release(authenticated)
        return socket

    async def _serve_lines(
        self,
        request: web.Request,
        socket: web.WebSocketResponse,
        token: str | None,
        authenticated: bool,
    ) -> None:
        session = Session(
            self.kernel, f"ws-{next(self._ids)}", websocket=True, token=token,
            observer=request.query.get("mode") == "observe", peer=request.remote or "?",
            guard=self._login_guard,
        )
        if request.transport is not None:
            session.outbox.on_overflow = request.transport.abort
        session.start()
        writer = asyncio.create_task(_write_lines(session, socket))
        try:
            async with self.idle_limit(socket, authenticated) as idle:
                await self._pump(request, socket, session, idle, authenticated)
        finally:
            await session.close()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await writer

    async def _pump(
        self,
        request: web.Request,
        socket: web.WebSocketResponse,
        session: Session,
        idle: asyncio.Timeout,
        authenticated: bool,
    ) -> None:
        def gone() -> bool:
            return session.closed or request.transport is None or request.transport.is_closing()

        async for message in socket:
            if message.type not in (WSMsgType.TEXT, WSMsgType.BINARY):
                continue
            idle.reschedule(self.idle_deadline(authenticated))
            await _feed(session, message.data, gone)


async def _feed(session: Session, data: str | bytes, gone: Callable[[], bool]) -> None:
    """One message, a slice at a time, through the session's one input path
    (``Session.feed``: paced, a loop turn between slices, waiting while its backlog is full;
    realtime bytes acted on as they arrive, whatever lines wait in front of them); the rest
    is dropped once the client is gone. Text goes the byte path UTF-8 encoded (a realtime
    code point such as U+0091 is then ``C2 91``, which the protocol reads as that byte)."""
    size, start = len(data), 0
    while True:
        if gone():
            return
        end = start + min(SLICE_CHARS, session.read_size)
        piece = data[start:end]
        raw = piece.encode("utf-8", "surrogatepass") if isinstance(piece, str) else piece
        await session.feed(raw, final=end >= size, gone=gone)
        await asyncio.sleep(0)  # a large message must not hold the loop: one slice a turn
        if end >= size:
            return
        start = end


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
