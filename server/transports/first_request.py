"""HTTP connections that have not yet sent a whole request: few, and not for long.

A client that opens connections and sends half a request holds a descriptor each for as long
as the server waits; 1,100 of them used to fill the descriptor table, so that the operator's
TCP sender connected but got no banner until they timed out. Until its first request has
arrived whole (the middleware calls :meth:`FirstRequestGuard.arrived`), a connection is
*pending*: at most ``[http] max_pending_requests`` are, a further one is closed on arrival,
and each is closed after ``[http] first_request_timeout_s``. A browser's idle preconnect
socket closed this way is simply opened again.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from aiohttp import web

log = logging.getLogger("motiond.http")
ProtocolFactory = Callable[[], asyncio.Protocol]


class FirstRequestGuard:
    """Counts and times the pending connections of one HTTP listener."""

    def __init__(self, max_pending: int, deadline_s: float) -> None:
        self.max_pending, self.deadline_s = max_pending, deadline_s
        self._timers: dict[int, asyncio.TimerHandle] = {}  # by id() of aiohttp's handler
        self.refused = 0

    @property
    def pending(self) -> int:
        return len(self._timers)

    def wrap(self, factory: ProtocolFactory) -> ProtocolFactory:
        """The listener's protocol factory, guarded."""
        return lambda: _Guarded(factory(), self)

    def arrived(self, handler: object) -> None:
        """A whole request arrived on ``handler``'s connection: it is pending no more."""
        timer = self._timers.pop(id(handler), None)
        if timer is not None:
            timer.cancel()

    def _admit(self, handler: object, transport: asyncio.BaseTransport) -> bool:
        if len(self._timers) >= self.max_pending:
            if self.refused == 0:
                log.warning("more than %d HTTP connections without a whole request: further "
                            "ones are closed at once", self.max_pending)
            self.refused += 1
            _drop(transport)
            return False
        self.refused = 0
        loop = asyncio.get_running_loop()
        self._timers[id(handler)] = loop.call_later(self.deadline_s, _drop, transport)
        return True

    def _gone(self, handler: object) -> None:
        self.arrived(handler)


def _drop(transport: asyncio.BaseTransport) -> None:
    """Close at once, whatever is unsent (a half-sent request gets no answer)."""
    if isinstance(transport, asyncio.WriteTransport):
        transport.abort()
    else:
        transport.close()


class _Guarded(asyncio.Protocol):
    """aiohttp's request handler, admitted and timed by the guard; everything else passes."""

    def __init__(self, inner: asyncio.Protocol, guard: FirstRequestGuard) -> None:
        self.inner, self.guard = inner, guard
        self.admitted = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.admitted = self.guard._admit(self.inner, transport)  # noqa: SLF001
        if self.admitted:
            self.inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self.guard._gone(self.inner)  # noqa: SLF001
        if self.admitted:
            self.inner.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self.admitted:
            self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self.inner.eof_received() if self.admitted else None

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


class GuardedSite(web.TCPSite):
    """aiohttp's TCP site, its connections passed through a :class:`FirstRequestGuard`."""

    def __init__(self, runner: web.AppRunner, host: str, port: int,
                 guard: FirstRequestGuard, **kwargs: Any) -> None:
        super().__init__(runner, host, port, **kwargs)
        self.guard = guard

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site; TCPSite's own start is replaced
        server = self._runner.server
        assert server is not None
        self._server = await asyncio.get_running_loop().create_server(
            self.guard.wrap(server), self._host, self._port, backlog=self._backlog,
            reuse_address=self._reuse_address, reuse_port=self._reuse_port)
