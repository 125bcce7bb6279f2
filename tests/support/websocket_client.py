"""A WebSocket client for tests on aiohttp's client (the one WebSocket stack motiond has).

``connect(url)`` is awaited or used with ``async with``; the connection sends and receives
whole messages, iterates until the server closes, and keeps the server's close code. A refused
handshake raises :class:`InvalidStatus` (``.response.status_code``); a closed connection
raises :class:`ConnectionClosed`. Defaults as a browser: per-message deflate offered, and
messages from the server up to ``max_size`` bytes (1 MiB; None: unbounded);
``receive_buffer_bytes`` shrinks the socket's receive buffer (a client that reads slowly).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Generator
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import aiohttp

DEFAULT_MAX_SIZE = 1 << 20


class WebSocketException(Exception):
    """Anything a connection can fail with."""


class ConnectionClosed(WebSocketException):
    """The connection is closed (by either side)."""


@dataclass(frozen=True)
class Response:
    status_code: int


class InvalidStatus(WebSocketException):
    """The server answered the handshake with another status than 101."""

    def __init__(self, status_code: int) -> None:
        super().__init__(f"server rejected WebSocket connection: HTTP {status_code}")
        self.response = Response(status_code)


class ClientConnection:
    """One open connection and the session it owns."""

    def __init__(self, session: aiohttp.ClientSession, ws: aiohttp.ClientWebSocketResponse):
        self._session = session
        self._ws = ws
        self._close_code: int | None = None  # the code in the server's close frame

    @property
    def close_code(self) -> int | None:
        """The server's close code (aiohttp's own when none arrived, as 1006)."""
        return self._close_code if self._close_code is not None else self._ws.close_code

    @property
    def transport(self) -> asyncio.Transport:
        """The TCP transport (``abort()`` drops the connection without a close frame)."""
        return self._ws._writer.transport  # type: ignore[no-any-return]

    async def send(self, message: str | bytes) -> None:
        try:
            if isinstance(message, str):
                await self._ws.send_str(message)
            else:
                await self._ws.send_bytes(message)
        except (ConnectionError, aiohttp.ClientConnectionError, RuntimeError) as exc:
            raise ConnectionClosed(str(exc)) from exc

    async def recv(self) -> str | bytes:
        message = await self._ws.receive()
        if message.type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY):
            return message.data  # type: ignore[no-any-return]
        if message.type is aiohttp.WSMsgType.CLOSE and self._close_code is None:
            self._close_code = int(message.data)
        await self._session.close()
        raise ConnectionClosed(f"closed: {self._ws.close_code} ({message.type.name})")

    async def close(self) -> None:
        try:
            await self._ws.close()
        finally:
            await self._session.close()

    async def __aiter__(self) -> AsyncIterator[str | bytes]:
        while True:
            try:
                yield await self.recv()
            except ConnectionClosed:
                return


class connect:  # noqa: N801 - used as a function: ``await connect(url)``
    """Open a connection to ``url`` (``ws://``)."""

    def __init__(self, url: str, *, origin: str | None = None,
                 max_size: int | None = DEFAULT_MAX_SIZE,
                 compression: str | None = "deflate",
                 receive_buffer_bytes: int | None = None) -> None:
        self.url = url
        self.receive_buffer_bytes = receive_buffer_bytes
        self.origin = origin
        self.max_size = max_size
        self.compression = compression
        self.connection: ClientConnection | None = None

    async def open(self) -> ClientConnection:
        session = aiohttp.ClientSession(connector=self._connector())
        try:
            ws = await session.ws_connect(
                self.url, origin=self.origin, max_msg_size=self.max_size or 0,
                compress=15 if self.compression else 0, autoclose=True)
        except aiohttp.WSServerHandshakeError as exc:
            await session.close()
            raise InvalidStatus(exc.status) from exc
        except BaseException:
            await session.close()
            raise
        self.connection = ClientConnection(session, ws)
        return self.connection

    def _connector(self) -> aiohttp.TCPConnector:
        size = self.receive_buffer_bytes
        if size is None:
            return aiohttp.TCPConnector()

        def small_buffer(addr_info: Any) -> socket.socket:
            family, kind, protocol = addr_info[:3]
            sock = socket.socket(family, kind, protocol)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
            return sock

        return aiohttp.TCPConnector(socket_factory=small_buffer)

    def __await__(self) -> Generator[Any, None, ClientConnection]:
        return self.open().__await__()

    async def __aenter__(self) -> ClientConnection:
        return await self.open()

    async def __aexit__(self, kind: type[BaseException] | None, error: BaseException | None,
                        trace: TracebackType | None) -> None:
        if self.connection is not None:
            await self.connection.close()
