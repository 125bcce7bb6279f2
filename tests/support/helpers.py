"""Test helpers: run an App on a clock and stop it cleanly."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

from server.app import App, TransportFactory
from server.config import Config
from server.runtime.clock import Clock, VirtualClock
from server.runtime.dispatcher import SystemSource

SOURCE = SystemSource()


@contextlib.asynccontextmanager
async def running(config: Config, clock: Clock | None = None,
                  transports: list[TransportFactory] | None = None) -> AsyncIterator[App]:
    """An App serving until the block ends (virtual clock unless one is given)."""
    app = App(config, clock=clock or VirtualClock(), transports=transports)
    task = asyncio.create_task(app.run())
    ready = asyncio.create_task(app.ready.wait())
    done, _ = await asyncio.wait({task, ready}, return_when=asyncio.FIRST_COMPLETED)
    if task in done:
        ready.cancel()
        task.result()
    try:
        yield app
    finally:
        app.request_stop()
        await asyncio.wait_for(task, 5)


async def submit_all(app: App, lines: list[str]) -> list[list[str]]:
    """Submit lines in order as the system source; returns each line's messages."""
    return [await app.kernel.dispatcher.submit(line, SOURCE) for line in lines]
