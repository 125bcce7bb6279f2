"""What waits to be published: a bounded FIFO of replies and events, and one status slot.

Nothing that produces a message ever waits for the broker. The status slot holds only the
latest status (a newer one replaces an unsent one: stale status is dropped); replies and events
queue up to ``limit`` messages and then the oldest is dropped and counted. The sender (one task
per broker connection) takes queued messages first, then the status.
"""

from __future__ import annotations

import asyncio
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Outgoing:
    topic: str
    payload: bytes
    retain: bool = False


class Outbox:
    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.dropped = 0  # replies and events dropped because the queue was full
        self.stale = 0  # status updates replaced before they were sent
        self._queue: deque[Outgoing] = deque()
        self._status: Outgoing | None = None
        self._ready = asyncio.Event()

    def __len__(self) -> int:
        return len(self._queue) + (self._status is not None)

    def put(self, message: Outgoing) -> None:
        """Queue a reply or an event; past ``limit`` the oldest is dropped."""
        if len(self._queue) >= self.limit:
            self._queue.popleft()
            self.dropped += 1
        self._queue.append(message)
        self._ready.set()

    def put_status(self, message: Outgoing) -> None:
        """The latest status; an unsent older one is dropped."""
        if self._status is not None:
            self.stale += 1
        self._status = message
        self._ready.set()

    def restore_status(self, message: Outgoing) -> None:
        """A status that could not be sent goes back, unless a newer one came meanwhile."""
        if self._status is None:
            self._status = message

    def take(self) -> Outgoing | None:
        """The next message, or None when there is none."""
        if self._queue:
            return self._queue.popleft()
        message, self._status = self._status, None
        return message

    async def get(self) -> Outgoing:
        """Wait for the next message."""
        while (message := self.take()) is None:
            self._ready.clear()
            await self._ready.wait()
        return message
