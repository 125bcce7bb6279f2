"""Raw TCP ("telnet") transport: one :class:`~server.session.Session` per client."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from typing import TYPE_CHECKING

from server.session import Session

if TYPE_CHECKING:
    from server.kernel import Kernel

log = logging.getLogger("motiond.tcp")
READ_CHUNK = 4096


class TcpTransport:
    """Listens on ``[tcp] host:port``; several clients at once, each isolated."""

    name = "tcp"

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.config = kernel.config.core.tcp
        self._server: asyncio.Server | None = None
        self._clients: dict[asyncio.Task[None], asyncio.StreamWriter] = {}
        self._ids = itertools.count(1)
        self.port = self.config.port

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, self.config.host, self.config.port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("TCP listening on %s:%d", self.config.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for writer in list(self._clients.values()):
            writer.transport.abort()  # each client task then ends on its own
        if self._clients:
            await asyncio.wait(list(self._clients), timeout=1.0)
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._clients) >= self.config.max_connections:
            writer.write(b"error: too many connections\r\n")
            writer.close()
            return
        self._clients[task] = writer
        peer = writer.get_extra_info("peername")
        session = Session(self.kernel, f"tcp-{next(self._ids)}")
        log.info("%s connected from %s", session.name, peer)
        try:
            await serve_stream(session, reader, writer)
        finally:
            self._clients.pop(task, None)
            log.info("%s disconnected", session.name)


async def serve_stream(
    session: Session, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
) -> None:
    """Pump bytes between a stream pair and a session until either side ends."""
    session.outbox.on_overflow = writer.transport.abort
    session.start()
    writer_task = asyncio.create_task(_write_loop(session, writer))
    try:
        while not session.closed:
            data = await reader.read(READ_CHUNK)
            if not data:
                break
            session.receive_data(data)
            await session.wait_room()
            await asyncio.sleep(0)  # buffered input must not hold the loop: one chunk a turn
    except (ConnectionError, OSError):
        pass
    finally:
        await session.close()
        writer_task.cancel()
        with contextlib.suppress(asyncio.CancelledError, ConnectionError, OSError):
            await writer_task
        writer.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(writer.wait_closed(), 1.0)


async def _write_loop(session: Session, writer: asyncio.StreamWriter) -> None:
    while True:
        data = await session.outbox.get()
        if data is None:
            if session.outbox.overflowed:
                log.warning("%s: client is not reading; disconnected", session.name)
                writer.transport.abort()
            return
        writer.write(data)
        await writer.drain()
