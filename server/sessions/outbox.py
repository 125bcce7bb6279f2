"""A bounded queue of outgoing data for one client, drained by that client's writer task.

Putting never waits: a client that falls behind by more than the bound overflows, its queue
closes and ``on_overflow`` runs (the transport aborts the connection), so a slow reader can
never stall motion or other clients (DESIGN.md rule 5).
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

Item = TypeVar("Item", str, bytes)


class BoundedQueue(Generic[Item]):
    """Items with a size each; at most ``limit`` in total (bytes, frames...)."""

    def __init__(self, limit: int, size: Callable[[Item], int] = len) -> None:
        self.limit = limit
        self._size_of: Callable[[Item], int] = size
        self.on_overflow: Callable[[], None] = lambda: None
        self.overflowed = False
        self.closed = False
        self._items: deque[Item] = deque()
        self._size = 0
        self._ready = asyncio.Event()

    def put(self, item: Item) -> bool:
        """Queue an item; False (and the queue closes) when the client is not keeping up."""
        if self.closed:
            return False
        size = self._size_of(item)
        if self._size + size > self.limit:
            self.overflowed = True
            self.close()
            self.on_overflow()
            return False
        self._items.append(item)
        self._size += size
        self._wake()
        return True

    def _wake(self) -> None:
        """An item was queued: wake the writer."""
        self._ready.set()

    async def wait(self) -> bool:
        """Wait for an item; False once closed (after an overflow, at once) and drained."""
        while not self._items:
            if self.closed:
                return False
            self._ready.clear()
            await self._ready.wait()
        return not (self.closed and self.overflowed)

    async def get_one(self) -> Item | None:
        """The next item, or None once closed."""
        if not await self.wait():
            return None
        item = self._items.popleft()
        self._size -= self._size_of(item)
        return item

    async def get_all(self) -> list[Item] | None:
        """Everything queued so far, or None once closed."""
        if not await self.wait():
            return None
        items = list(self._items)
        self._items.clear()
        self._size = 0
        return items

    def close(self) -> None:
        """Stop accepting; the writer drains what is left (nothing, after an overflow)."""
        self.closed = True
        self._ready.set()
