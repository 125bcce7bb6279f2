"""The JSON API: JSON-RPC 2.0 over WebSocket at ``/api`` and streamed uploads at ``/upload``.

Composed explicitly: :func:`http_with_api` builds the HTTP transport with :func:`install` as a
route hook, and the method table is composed from ``CORE_METHODS`` (:mod:`server.api.methods`),
``JOB_METHODS`` (:mod:`server.api.jobs`) and the methods modules contribute (documented in
``docs/API.md``). Every request runs in its own task owned by its connection, so a
``gcode.send`` waiting for planner room never delays a ``machine.hold``; G-code from one
connection still executes in order (a per-connection lock, then the dispatcher's FIFO lock).
Replies and notifications share one bounded :class:`~server.api.telemetry.Channel` per connection:
a client that stops reading is disconnected, never waited for.

Access: a request naming a host not in ``[http] allowed_hosts`` is refused (403), and so is a
browser page from another origin unless ``[http] allowed_origins`` names it; with
``[http] token`` set, a connection may only query until it presents the token
(``/api?token=...``, an ``X-Motiond-Token`` header or the ``server.auth`` method; an observer,
``?mode=observe``, never controls), and uploads need it too. Before the token a connection has
its own, smaller, connection limit and message size and is closed once idle; frames are decoded
by :mod:`server.api.jsonrpc`, which refuses deep nesting and non-finite numbers.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import time
from collections.abc import AsyncIterator
from typing import TYPE_CHECKING, Any

from aiohttp import WSCloseCode, WSMsgType, web

from server.api.drawings import DRAWING_METHODS
from server.api.jobs import JOB_METHODS
from server.api.jsonrpc import INTERNAL, INVALID_REQUEST, BadRequest, decode_request
from server.api.materials import MATERIAL_METHODS
from server.api.methods import CORE_METHODS, Methods, RpcError, command_error, compose
from server.api.placement import PLACEMENT_METHODS
from server.api.telemetry import Channel, Publisher, encode
from server.errors import CommandError, Error
from server.transports.access import tokens_equal
from server.transports.websocket import HEARTBEAT_S, HttpTransport, presented_token

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

log = logging.getLogger("motiond.api")
MAX_IN_FLIGHT = 64
UPLOAD_CHUNK_BYTES = 1 << 16
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
        self,
        api: JsonApi,
        socket: web.WebSocketResponse,
        name: str,
        authenticated: bool,
        observer: bool,
    ) -> None:
        self.api = api
        self.socket = socket
        self.name = name
        self.authenticated = authenticated  # presented the token (or none is needed)
        self.observer = observer  # ?mode=observe: watches, never controls
        self.can_control = authenticated and not observer
        self.idle: asyncio.Timeout | None = None
        self.channel = Channel()
        self.gcode_lock = asyncio.Lock()
        self.closing = False
        self._tasks: set[asyncio.Task[None]] = set()
        rate = api.http.max_requests_per_s
        self._bucket = TokenBucket(rate, burst=max(1.0, rate))

    def authenticate(self) -> None:
        """The token was presented: control (unless an observer), the limits of a trusted
        connection, no idle timeout."""
        if not self.authenticated:
            self.authenticated = True
            self.api.transport.slots.promote()
        self.can_control = not self.observer
        if self.idle is not None:
            self.idle.reschedule(None)

    def receive(self, text: str) -> bool:
        """A text frame: one JSON-RPC request or notification. Whether it was one."""
        try:
            message = decode_request(text)
        except BadRequest as exc:
            self.reply(exc.request_id, error=(exc.code, exc.message, None))
            return False
        if len(self._tasks) >= MAX_IN_FLIGHT:
            self.reply(message.get("id"), error=(TOO_BUSY, "too many requests in flight", None))
            return False
        if not self._bucket.take(time.monotonic()):
            error = (RATE_LIMITED, "too many requests per second", None)
            self.reply(message.get("id"), error=error)
            return False
        task = asyncio.get_running_loop().create_task(self._run(message), name=self.name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return True

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
        table = compose(CORE_METHODS, JOB_METHODS, PLACEMENT_METHODS, DRAWING_METHODS,
                        MATERIAL_METHODS,
                        modules=self.kernel.api_methods.values())
        self.methods = Methods(self, table)
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
    def token_ok(self, token: str | None, request: web.Request | None = None) -> bool:
        """The token (or none is needed, or ``request`` comes from a trusted client)."""
        expected = self.http.token or os.environ.get("MOTIOND_TOKEN") or None
        if expected is None or (request is not None and self.transport.trusted(request)):
            return True
        return tokens_equal(token, expected)

    # -- /api -------------------------------------------------------------------------------
    async def socket(self, request: web.Request) -> web.StreamResponse:
        authenticated = self.token_ok(presented_token(request), request)
        self.transport.admit(request, authenticated)
        socket = web.WebSocketResponse(
            heartbeat=HEARTBEAT_S, max_msg_size=self.http.api_max_message_bytes, compress=False
        )  # frames are encoded once for all
        observer = request.query.get("mode") == "observe"
        connection = Connection(self, socket, f"api-{next(self._ids)}", authenticated, observer)
        try:
            await socket.prepare(request)
            await self._serve(request, connection)
        finally:
            self.transport.slots.release(connection.authenticated)
        return socket

    async def _serve(self, request: web.Request, connection: Connection) -> None:
        if request.transport is not None:
            connection.channel.on_overflow = request.transport.abort
        self.connections.add(connection)
        writer = asyncio.get_running_loop().create_task(_write(connection), name="api-writer")
        idle_limit = self.transport.idle_limit(connection.socket, connection.authenticated)
        try:
            async with idle_limit as idle:
                connection.idle = idle
                await self._receive(connection)
        finally:
            self.connections.discard(connection)
            await connection.close()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await writer

    async def _receive(self, connection: Connection) -> None:
        """Requests until the socket closes; before the token, messages are smaller and only
        a well-formed request puts off the idle timeout."""
        socket = connection.socket
        async for message in socket:
            if message.type is WSMsgType.BINARY:
                connection.reply(None, error=(INVALID_REQUEST, "send JSON as text", None))
            if message.type is not WSMsgType.TEXT:
                continue
            if not connection.authenticated and self._too_big(message.data):
                too_big = b"too big without the token"
                await socket.close(code=WSCloseCode.MESSAGE_TOO_BIG, message=too_big)
                return
            if connection.receive(message.data) and connection.idle is not None:
                connection.idle.reschedule(self.transport.idle_deadline(connection.authenticated))

    def _too_big(self, text: str) -> bool:
        limit = self.http.unauthenticated_max_message_bytes
        return len(text) > limit or len(text.encode("utf-8", "surrogatepass")) > limit

    # -- /upload ----------------------------------------------------------------------------
    async def upload(self, request: web.Request) -> web.Response:
        """``POST /upload?name=NAME``: the body, streamed into the job folder."""
        encoding = request.headers.get("Content-Encoding", "identity").strip().lower()
        if encoding != "identity":  # inflating would cost loop time before any check
            return _json_error(415, 44, f"Content-Encoding {encoding!r} is not accepted: "
                               "upload the file as it is")
        if not self.transport.origin_allowed(request):
            return _json_error(403, Error.AUTH_REQUIRED, "origin not allowed")
        if not self.token_ok(presented_token(request), request):
            return _json_error(401, Error.AUTH_REQUIRED, "a token is required to upload")
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
    """A refusal; the connection then closes without reading the rest of the body."""
    response = web.json_response({"error": {"code": code, "message": message}}, status=status)
    response.force_close()
    return response


API_KEY = web.AppKey("motiond.api", JsonApi)


def install(transport: HttpTransport, app: web.Application) -> None:
    """The route hook: ``/api``, ``/upload`` and the publisher's lifetime."""
    api = JsonApi(transport)
    app[API_KEY] = api
    app.router.add_get("/api", api.socket)
    app.router.add_post("/upload", api.upload)
    app.cleanup_ctx.append(api.lifespan)
    app.on_shutdown.append(api.on_shutdown)


def http_with_api(kernel: Kernel) -> HttpTransport:
    """The HTTP transport with the JSON API's routes: what ``motiond`` serves."""
    return HttpTransport(kernel, route_hooks=(install,))
