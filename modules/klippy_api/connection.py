"""One connection of the API socket: reading within the loop budget, writing bounded.

:func:`serve` reads, frames (:class:`wire.Framer`) and hands each request to the connection's
:class:`~modules.klippy_api.session.Session`, one at a time within the hub's
:class:`~modules.klippy_api.budget.LoopBudget`; while it waits for the budget it does not
read, so a flooding client is held back by its own socket (back-pressure), never buffered.
What the session sends waits in :class:`Connection`'s queue, bounded in messages and in bytes:
a client that does not read its answers is disconnected, never waited for.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

from modules.klippy_api import wire
from modules.klippy_api.hub import Hub
from modules.klippy_api.session import Session

OUTGOING_MESSAGES = 1000
OUTGOING_BYTES = 4 << 20
READ_BYTES = 65536
REFUSE_WAIT_S = 0.5  # a refused client is answered and closed within this
REFUSE_BYTES = 4 << 20  # and this much of what it sends is read (and dropped) meanwhile


class Connection:
    """A client's writer, its bounded outgoing queue and its session."""

    def __init__(self, writer: asyncio.StreamWriter, hub: Hub) -> None:
        self.writer = writer
        self.outgoing: asyncio.Queue[bytes] = asyncio.Queue()
        self.queued_bytes = 0
        self.closed = False
        self.session = Session(hub, self.send)

    def send(self, message: dict[str, Any]) -> None:
        """Queue a message; a client that lets :data:`OUTGOING_MESSAGES` or
        :data:`OUTGOING_BYTES` pile up does not read: it is dropped."""
        if self.closed:
            return
        data = wire.encode(message)
        if (self.outgoing.qsize() >= OUTGOING_MESSAGES
                or self.queued_bytes + len(data) > OUTGOING_BYTES):
            self.close()
            return
        self.queued_bytes += len(data)
        self.outgoing.put_nowait(data)

    def close(self) -> None:
        """Close the socket and free what waits to be sent (the reader then ends)."""
        self.closed = True
        while not self.outgoing.empty():
            self.outgoing.get_nowait()
        self.queued_bytes = 0
        self.writer.close()

    async def drain(self) -> None:
        """Write queued messages until cancelled or the peer is gone."""
        try:
            while True:
                data = await self.outgoing.get()
                self.queued_bytes -= len(data)
                self.writer.write(data)
                await self.writer.drain()
        except ConnectionError:
            self.close()  # the reader then ends the connection


async def serve(connection: Connection, reader: asyncio.StreamReader, hub: Hub,
                log: logging.Logger) -> None:
    """Serve ``connection`` until the peer goes or breaks the framing; then drop its
    waiting scripts and buffers."""
    session = connection.session
    try:
        async with asyncio.TaskGroup() as group:
            sender = group.create_task(connection.drain(), name="klippy-api-send")
            scripts = group.create_task(session.scripts.run(), name="klippy-api-scripts")
            try:
                await _read(reader, session, hub)
            except (wire.FramingError, ConnectionError) as exc:
                log.warning("API client dropped: %s", exc)
            sender.cancel()
            scripts.cancel()
    finally:
        session.close()
        connection.close()


async def _read(reader: asyncio.StreamReader, session: Session, hub: Hub) -> None:
    framer, budget = wire.Framer(), hub.budget
    while data := await reader.read(READ_BYTES):
        framer.push(data)
        while True:
            await budget.turn()
            request = framer.pop()
            if request is None:
                break
            await session.on_request(request)


async def refuse(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, message: str,
                 wait_s: float = REFUSE_WAIT_S) -> None:
    """Tell a client it is not served: ``message`` as the error answer to its first request
    (its id read from the request's start, as Moonraker writes it; null when none comes),
    then close, within ``wait_s``. What it sends is read and dropped unparsed meanwhile (at
    most :data:`REFUSE_BYTES`): a client whose writes failed would never read why."""
    first, replied, seen_bytes = b"", False, 0
    with contextlib.suppress(TimeoutError, ConnectionError):
        async with asyncio.timeout(wait_s):
            while seen_bytes <= REFUSE_BYTES and (data := await reader.read(READ_BYTES)):
                first, seen_bytes = first or data, seen_bytes + len(data)
                if not replied and wire.ETX in data:
                    writer.write(wire.encode(wire.error(wire.leading_id(first), message)))
                    replied = True
    if not replied:
        writer.write(wire.encode(wire.error(wire.leading_id(first), message)))
    writer.close()
