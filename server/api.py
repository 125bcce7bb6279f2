"""The JSON API: JSON-RPC 2.0 over WebSocket at ``/api`` and streamed uploads at ``/upload``.

Registered on :class:`~server.transports.websocket.HttpTransport` through its ``route_hooks``
when this module is imported. Every request runs in its own task owned by its connection, so a
``gcode.send`` waiting for planner room never delays a ``machine.hold``; G-code from one
connection still executes in order (a per-connection lock, then the dispatcher's FIFO lock).
Replies and notifications share one bounded :class:`~server.telemetry.Channel` per connection:
a client that stops reading is disconnected, never waited for. Methods are listed in
:mod:`server.api_methods` and documented in ``docs/API.md``.

Access: a browser page from another origin is refused unless ``[http] allowed_origins`` names
it; with ``[http] token`` set, a connection may only query until it presents the token
(``/api?token=...`` or the ``server.auth`` method), and uploads need it too.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import itertools
import json
import logging
import os
import time
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any

from aiohttp import WSMsgType, web

import server.api_jobs  # noqa: F401 - registers the settings.* and job.* methods
from server.api_methods import Methods, RpcError, command_error
from server.errors import AUTH_REQUIRED, CommandError
from server.telemetry import Channel, Publisher, encode
from server.transports.websocket import HttpTransport, origin_allowed

if TYPE_CHECKING:
    from server.kernel import Kernel

log = logging.getLogger("motiond.api")
MAX_IN_FLIGHT = 64
MAX_MESSAGE_BYTES = 64 << 20
UPLOAD_CHUNK_BYTES = 1 << 16
PARSE_ERROR, INVALID_REQUEST, METHOD_NOT_FOUND, INVALID_PARAMS, INTERNAL = (
    -32700,
    -32600,
    -32601,
    -32602,
    -32603,
)
TOO_BUSY = -32000
RATE_LIMITED = -32001


class TokenBucket:
    """A request-rate limit: ``rate`` per second on average, bursts up to ``burst``."""

    def __init__(self, rate: float, burst: float) -> None:
        self.rate, self.burst = rate, burst
        self.tokens, self.last_s = burst, time.monotonic()

    def take(self, now_s: float) -> bool:
        self.tokens = min(self.burst, self.tokens + (now_s - self.last_s) * self.rate)
        self.last_s = now_s
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


class Connection:
    """One ``/api`` client: its channel, its request tasks and its right to control."""

    def __init__(
        self, api: JsonApi, socket: web.WebSocketResponse, name: str, can_control: bool
    ) -> None:
        self.api = api
        self.socket = socket
        self.name = name
        self.can_control = can_control
        self.channel = Channel()
        self.gcode_lock = asyncio.Lock()
        self.closing = False
        self._tasks: set[asyncio.Task[None]] = set()
        rate = api.http.max_requests_per_s
        self._bucket = TokenBucket(rate, burst=max(1.0, rate))

    def receive(self, text: str) -> None:
        """A text frame: one JSON-RPC request or notification."""
        try:
            message = json.loads(text)
        except ValueError:
            self.reply(None, error=(PARSE_ERROR, "parse error: not JSON", None))
            return
        if (
            not isinstance(message, dict)
            or message.get("jsonrpc") != "2.0"
            or not isinstance(message.get("method"), str)
        ):
            request_id = message.get("id") if isinstance(message, dict) else None
            self.reply(
                request_id,
                error=(
                    INVALID_REQUEST,
                    "not a JSON-RPC 2.0 request (batches are not supported)",
                    None,
                ),
            )
            return
        if len(self._tasks) >= MAX_IN_FLIGHT:
            self.reply(message.get("id"), error=(TOO_BUSY, "too many requests in flight", None))
            return
        if not self._bucket.take(time.monotonic()):
            error = (RATE_LIMITED, "too many requests per second", None)
            self.reply(message.get("id"), error=error)
            return
        task = asyncio.get_running_loop().create_task(self._run(message), name=self.name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def reply(
        self, request_id: Any, result: Any = None, error: tuple[int, str, Any] | None = None
    ) -> None:
        """Queue a response (not for notifications, which have no id)."""
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": request_id}
        if error is None:
            message["result"] = result
        else:
            code, text, data = error
            message["error"] = {"code": code, "message": text}
            if data is not None:
                message["error"]["data"] = data
        try:
            frame = encode(message)
        except (TypeError, ValueError) as exc:  # not JSON-able (NaN, an object): say so
            log.exception("cannot encode the reply to request %r", request_id)
            frame = encode(
                {
                    "jsonrpc": "2.0",
                    "id": request_id,
                    "error": {"code": INTERNAL, "message": f"internal error: {exc}"},
                }
            )
        self.channel.offer(frame)

    async def _run(self, message: dict[str, Any]) -> None:
        result: Any = None
        error: tuple[int, str, Any] | None = None
        try:
            result = await self.api.methods.call(self, message["method"], message.get("params"))
        except RpcError as exc:
            error = (exc.code, exc.message, exc.data)
        except CommandError as exc:
            error = command_error(exc)
        except Exception as exc:  # noqa: BLE001 - answer, log, keep serving
            log.exception("API method %s failed", message["method"])
            error = (INTERNAL, f"internal error: {exc!r}", None)
        if "id" in message:  # a request without an id is a notification: no reply
            self.reply(message["id"], result, error)

    async def close(self) -> None:
        """Stop taking requests; a G-code line already executing completes (all or nothing)."""
        self.closing = True
        self.api.publisher.unsubscribe(self.channel)
        self.channel.close()
        if self._tasks:
            await asyncio.wait(list(self._tasks))


class JsonApi:
    """The ``/api`` and ``/upload`` endpoints of one HTTP transport."""

    def __init__(self, transport: HttpTransport) -> None:
        self.transport = transport
        self.kernel: Kernel = transport.kernel
        self.http = transport.config
        self.publisher = Publisher(self.kernel)
        self.methods = Methods(self)
        self.connections: set[Connection] = set()
        self._ids = itertools.count(1)

    # -- lifecycle (aiohttp signals) --------------------------------------------------------
    async def lifespan(self, app: web.Application) -> AsyncIterator[None]:
        """Own the publisher task for as long as the HTTP app runs."""
        task = asyncio.get_running_loop().create_task(self.publisher.run(), name="api-publisher")
        try:
            yield
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def on_shutdown(self, app: web.Application) -> None:
        for connection in list(self.connections):
            connection.channel.close()
            with contextlib.suppress(Exception):
                await connection.socket.close(code=1001, message=b"server shutting down")

    # -- access -----------------------------------------------------------------------------
    def origin_allowed(self, request: web.Request) -> bool:
        """Same-origin pages, listed origins and non-browser clients (no Origin header)."""
        return origin_allowed(request, self.http.allowed_origins)

    def token_ok(self, token: str | None) -> bool:
        expected = self.http.token or os.environ.get("MOTIOND_TOKEN") or None
        return expected is None or (token is not None and hmac.compare_digest(token, expected))

    # -- /api -------------------------------------------------------------------------------
    async def socket(self, request: web.Request) -> web.StreamResponse:
        self.transport.admit(request)
        socket = web.WebSocketResponse(
            heartbeat=20, max_msg_size=MAX_MESSAGE_BYTES, compress=False
        )  # frames are encoded once for all
        await socket.prepare(request)
        connection = Connection(
            self,
            socket,
            f"api-{next(self._ids)}",
            self.token_ok(request.query.get("token")) and request.query.get("mode") != "observe",
        )
        if request.transport is not None:
            connection.channel.on_overflow = request.transport.abort
        self.connections.add(connection)
        self.transport.open_sockets += 1
        writer = asyncio.get_running_loop().create_task(_write(connection), name="api-writer")
        try:
            async for message in socket:
                if message.type is WSMsgType.TEXT:
                    connection.receive(message.data)
                elif message.type is WSMsgType.BINARY:
                    connection.reply(None, error=(INVALID_REQUEST, "send JSON as text", None))
        finally:
            self.connections.discard(connection)
            self.transport.open_sockets -= 1
            await connection.close()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await writer
        return socket

    # -- /upload ----------------------------------------------------------------------------
    async def upload(self, request: web.Request) -> web.Response:
        """``POST /upload?name=NAME``: the body, streamed into the job folder."""
        if not self.origin_allowed(request):
            return _json_error(403, AUTH_REQUIRED, "origin not allowed")
        token = request.query.get("token") or request.headers.get("X-Motiond-Token")
        if not self.token_ok(token):
            return _json_error(401, AUTH_REQUIRED, "a token is required to upload")
        name = request.query.get("name", "")
        limit = self.kernel.config.core.jobs.max_upload_bytes
        if request.content_length is not None and request.content_length > limit:
            return _json_error(413, 44, f"upload larger than {limit} bytes")
        chunks = request.content.iter_chunked(UPLOAD_CHUNK_BYTES)
        try:
            stored = await self.kernel.jobs.save_stream(name, chunks, limit)
        except CommandError as exc:
            code, message, data = command_error(exc)
            return web.json_response(
                {"error": {"code": code, "message": message, "data": data}}, status=400
            )
        result = {
            "name": stored.name,
            "size_bytes": stored.size_bytes,
            "modified_s": stored.modified_s,
        }
        self.publisher.broadcast(
            "job", "notify_filelist_changed", {"action": "upload", "file": result}
        )
        return web.json_response({"result": result})


async def _write(connection: Connection) -> None:
    while True:
        frame = await connection.channel.get()
        if frame is None:
            return
        await connection.socket.send_str(frame)


def _json_error(status: int, code: int, message: str) -> web.Response:
    return web.json_response({"error": {"code": code, "message": message}}, status=status)


API_KEY = web.AppKey("motiond.api", JsonApi)


def install(transport: HttpTransport, app: web.Application) -> None:
    """The route hook: ``/api``, ``/upload`` and the publisher's lifetime."""
    api = JsonApi(transport)
    app[API_KEY] = api
    app.router.add_get("/api", api.socket)
    app.router.add_post("/upload", api.upload)
    app.cleanup_ctx.append(api.lifespan)
    app.on_shutdown.append(api.on_shutdown)


if install not in HttpTransport.route_hooks:
    HttpTransport.route_hooks.append(install)
