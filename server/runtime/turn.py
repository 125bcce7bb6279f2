"""The dispatcher's order: one line runs at a time, the others wait first come, first served."""

from __future__ import annotations

import asyncio
from collections import deque


class Turn:
    """The dispatcher's order: one line runs at a time, the others wait first come, first
    served. Unlike ``asyncio.Lock`` it can be taken without a coroutine when it is
    :attr:`free`, and a released turn goes straight to the first waiter (``taken`` stays
    set): nobody arriving meanwhile overtakes it."""

    def __init__(self) -> None:
        self.taken = False
        self._waiters: deque[asyncio.Future[None]] = deque()

    @property
    def free(self) -> bool:
        """Nobody runs a line and nobody waits: the turn may be taken at once."""
        return not self.taken and not self._waiters

    async def take(self) -> None:
        """Wait for the turn (first come, first served)."""
        if self.free:
            self.taken = True
            return
        waiter = asyncio.get_running_loop().create_future()
        self._waiters.append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            if waiter.done() and not waiter.cancelled():
                self.release()  # handed the turn, cancelled before taking it: pass it on
            elif waiter in self._waiters:
                self._waiters.remove(waiter)
            raise

    def release(self) -> None:
        """End the current line's turn: the first waiter still waiting gets it."""
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return
        self.taken = False
