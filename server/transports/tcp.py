"""Raw TCP ("telnet") transport: one :class:`~server.sessions.session.Session` per client.

Reading: bytes are read in slices (``session.read_size``: 4096 bytes, 256 from a connection
that may not control, whose input is also paced) with a loop turn between slices, so a flood
from one client never holds the loop; the session takes every slice (``Session.feed``, which
also bounds what realtime bytes cost) (holding lines back
in its bounded backlog when its line queue is full, acting on realtime bytes at once) and the
read loop pauses only while that backlog is full.

Who may stay connected (``[tcp]``), so idle sockets cannot lock the operator out:

* at most ``max_connections`` at once. With a token set, connections that have not logged in
  may use at most ``max_connections - reserved_connections`` of them (at least one); a
  connection arriving beyond that gets a reserved slot on probation: its first line must be
  ``$AUTH=<token>``, within ``login_timeout_s``, else it is told why and closed. When every
  slot is taken, a newcomer replaces the oldest connection still on probation, so a client
  holding the token always gets in;
* a connection that has not logged in (token set) and receives nothing for
  ``idle_timeout_s`` is told why and closed, as is one that never sent a byte. A logged-in
  connection, or any connection that has sent something when no token is set, may stay idle
  for as long as it likes (Grbl senders sit idle for hours).

Every refusal is a ``[MSG:...]`` line before the connection closes.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from server.sessions.session import Session, line_token, login_guard

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

log = logging.getLogger("motiond.tcp")
DRAIN_ON_CLOSE_S = 1.0
# A read deadline: seconds to wait for the next byte and the reason given when none comes.
ReadDeadline = Callable[[int], "tuple[float, str] | None"]


class TcpTransport:
    """Listens on ``[tcp] host:port``; several clients at once, each isolated."""

    name = "tcp"

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.config = kernel.config.core.tcp
        self._server: asyncio.Server | None = None
        self._clients: dict[asyncio.Task[None], tuple[asyncio.StreamWriter, Session]] = {}
        self._ids = itertools.count(1)
        self._guard = login_guard(kernel)
        self.port = self.config.port

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, self.config.host, self.config.port)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("TCP listening on %s:%d", self.config.host, self.port)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
        for writer, _ in list(self._clients.values()):
            writer.transport.abort()  # each client task then ends on its own
        if self._clients:
            _, late = await asyncio.wait(list(self._clients), timeout=1.0)
            for task in late:  # one still pacing a flood: ended here, not by the loop's end
                task.cancel()
            if late:
                await asyncio.wait(late, timeout=1.0)
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.wait_closed()
            self._server = None
        self._guard.close()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        slot = self._slot()
        if slot is None:
            limit = self.config.max_connections
            writer.write(f"[MSG:too many connections ({limit} open); try again later]\r\n".encode())
            writer.close()
            return
        peer = writer.get_extra_info("peername")
        address = str(peer[0]) if isinstance(peer, tuple) else str(peer)
        session = Session(self.kernel, f"tcp-{next(self._ids)}", peer=address,
                          guard=self._guard, must_login=slot == "reserved")
        self._clients[task] = (writer, session)
        log.info("%s connected from %s%s", session.name, peer,
                 " (reserved slot: must log in)" if session.on_probation else "")
        try:
            await serve_stream(session, reader, writer, self._deadline(session))
        except asyncio.CancelledError:
            # Shutting down ends this connection: its task returns (asyncio's stream server
            # logs a client task that ends cancelled with a traceback, as if it had failed).
            log.debug("%s: ended by the shutdown", session.name)
        finally:
            self._clients.pop(task, None)
            log.info("%s disconnected", session.name)

    def _slot(self) -> str | None:
        """``"open"``, ``"reserved"`` (on probation) or None (refused) for a newcomer."""
        sessions = [session for _, session in self._clients.values() if not session.closed]
        if line_token(self.kernel) is None:
            return "open" if len(sessions) < self.config.max_connections else None
        if len(sessions) >= self.config.max_connections:
            waiting = [session for session in sessions if session.on_probation]
            if not waiting:
                return None
            waiting[0].end("a newer connection took this reserved slot")
            return "reserved"
        unauthenticated = sum(1 for session in sessions if not session.can_control)
        open_slots = max(1, self.config.max_connections - self.config.reserved_connections)
        return "open" if unauthenticated < open_slots else "reserved"

    def _deadline(self, session: Session) -> ReadDeadline:
        """How long ``session`` may stay silent (see the module docstring)."""
        config = self.config
        login_by_s = time.monotonic() + config.login_timeout_s

        def deadline(received_bytes: int) -> tuple[float, str] | None:
            if session.on_probation:
                return login_by_s - time.monotonic(), (
                    f"no $AUTH=<token> within {config.login_timeout_s:g} s in a reserved slot")
            if not session.can_control:
                return config.idle_timeout_s, (
                    f"idle for {config.idle_timeout_s:g} s without logging in")
            if received_bytes == 0:
                return config.idle_timeout_s, f"nothing received for {config.idle_timeout_s:g} s"
            return None

        return deadline


async def serve_stream(
    session: Session,
    reader: asyncio.StreamReader,
    writer: asyncio.StreamWriter,
    deadline: ReadDeadline | None = None,
) -> None:
    """Pump bytes between a stream pair and a session until either side ends.

    ``deadline(bytes received so far)`` bounds the wait for the next bytes: when it passes, the
    session ends with the reason given.
    """
    session.outbox.on_overflow = writer.transport.abort
    session.outbox.write_now = _writes_now(writer.transport)
    session.start()
    writer_task = asyncio.create_task(_write_loop(session, writer))
    received_bytes = 0

    def gone() -> bool:  # the client hung up (or reset): a flood's rest is not examined
        return reader.at_eof() or writer.transport.is_closing()

    try:
        while not session.closed:
            limit = None if deadline is None else deadline(received_bytes)
            read_size = session.read_size
            try:
                if limit is None:
                    data = await reader.read(read_size)
                else:
                    async with asyncio.timeout(max(0.0, limit[0])):
                        data = await reader.read(read_size)
            except TimeoutError:
                assert limit is not None
                session.end(f"closing: {limit[1]}")
                break
            if not data:
                break
            received_bytes += len(data)
            await session.feed(data, gone=gone)  # paced, sliced, waits while the backlog is full
            # More may be buffered (a full read): it must not hold the loop, one slice a turn.
            # A connection under a deadline also lets its lines run ($AUTH) before the next.
            if len(data) == read_size or limit is not None:
                await asyncio.sleep(0)
    except (ConnectionError, OSError):
        pass
    finally:
        await session.close()
        await _finish_writing(writer_task)
        writer.close()
        with contextlib.suppress(Exception):
            async with asyncio.timeout(1.0):
                await writer.wait_closed()


def _writes_now(transport: asyncio.WriteTransport) -> Callable[[bytes], bool]:
    """Write at once while the transport holds nothing unsent (so its buffer stays bounded by
    one write; a client that falls behind is left to the writer task and the outbox's bound)."""

    def write_now(data: bytes) -> bool:
        if transport.is_closing() or transport.get_write_buffer_size():
            return False
        transport.write(data)
        return True

    return write_now


async def _finish_writing(writer_task: asyncio.Task[None]) -> None:
    """Let the writer send what is queued (a last message), for a bounded time."""
    with contextlib.suppress(TimeoutError, asyncio.CancelledError, ConnectionError, OSError):
        async with asyncio.timeout(DRAIN_ON_CLOSE_S):
            await writer_task


async def _write_loop(session: Session, writer: asyncio.StreamWriter) -> None:
    while True:
        data = await session.outbox.get()
        if data is None:
            if session.outbox.overflowed:
                log.warning("%s: client is not reading; disconnected", session.name)
                writer.transport.abort()
            else:
                writer.close()  # the session ended: hang up once everything is sent
            return
        writer.write(data)
        await writer.drain()
