"""The running server: a kernel plus its transports, with an ordered, bounded shutdown.

Shutdown (SIGINT/SIGTERM, or :meth:`App.request_stop`) first stops motion and turns every tool
off (the kernel's ``shutdown`` event), then closes the transports, then cancels the kernel's
tasks; it is bounded by ``shutdown_timeout_s`` and calling it twice is harmless.

While it runs, a listener that cannot accept (out of descriptors) is logged once per burst, not
once a second with a traceback (:class:`~server.transports.accept_errors.AcceptErrorLog`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
from collections.abc import Callable
from typing import Protocol

from server.api.server import http_with_api
from server.config import Config
from server.kernel.kernel import Kernel
from server.runtime.clock import Clock, RealClock, VirtualClock
from server.transports.accept_errors import AcceptErrorLog
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport

log = logging.getLogger("motiond.app")


class Transport(Protocol):
    """A listener (TCP server, HTTP/WebSocket server, serial port) owned by the app."""

    name: str

    async def start(self) -> None:
        """Start listening; return once ready."""

    async def close(self) -> None:
        """Stop listening and close every connection; safe to call twice."""


TransportFactory = Callable[[Kernel], Transport]


def default_transports(config: Config) -> list[TransportFactory]:
    """The transports the config enables, in start order."""
    core = config.core
    factories: list[TransportFactory] = []
    if core.tcp.enabled:
        factories.append(TcpTransport)
    if core.http.enabled:
        factories.append(http_with_api)
    if core.serial.device or core.serial.pty:
        factories.append(SerialTransport)
    return factories


class App:
    """Owns the kernel task and the transports."""

    def __init__(
        self,
        config: Config,
        clock: Clock | None = None,
        transports: list[TransportFactory] | None = None,
        shutdown_timeout_s: float = 1.5,
    ) -> None:
        self.clock = clock or RealClock()
        self.kernel = Kernel(config, self.clock)
        self.transports = [factory(self.kernel) for factory in transports or ()]
        self.shutdown_timeout_s = shutdown_timeout_s
        self.ready = asyncio.Event()
        self._stop = asyncio.Event()
        self.closed_order: list[str] = []

    def request_stop(self) -> None:
        """Begin shutdown; repeated calls are harmless."""
        if not self._stop.is_set():
            log.info("shutting down")
            self.kernel.stop()
            self.closed_order.append("tools-off")
            self._stop.set()

    async def run(self) -> None:
        """Serve until :meth:`request_stop`."""
        accept_errors = AcceptErrorLog(asyncio.get_running_loop())
        accept_errors.install()
        try:
            await self._serve()
        finally:
            accept_errors.uninstall()

    async def _serve(self) -> None:
        async with asyncio.TaskGroup() as group:
            clock_task = None
            if isinstance(self.clock, VirtualClock):
                clock_task = group.create_task(self.clock.run(), name="virtual-clock")
            kernel_task = group.create_task(self.kernel.run(), name="kernel")
            await self.kernel.started.wait()
            try:
                for transport in self.transports:
                    await transport.start()
                # Everything start-up made lives as long as the process: keep it out of the
                # garbage collector's full scans, which otherwise stall the loop 15-20 ms.
                gc.freeze()
                self.ready.set()
                await self._stop.wait()
            finally:
                self.request_stop()
                await self._close_transports()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(asyncio.shield(kernel_task), self.shutdown_timeout_s)
                kernel_task.cancel()
                if clock_task is not None:
                    clock_task.cancel()

    async def _close_transports(self) -> None:
        for transport in self.transports:
            try:
                await asyncio.wait_for(transport.close(), self.shutdown_timeout_s)
            except TimeoutError:
                log.warning("transport %s did not close in time", transport.name)
            self.closed_order.append(f"close:{transport.name}")
