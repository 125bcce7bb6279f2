"""Clocks: one interface for real (event loop) time and virtual time.

Time is in seconds (``now_s``). ``sleep_until`` is the only way tasks wait for time, so the same
code runs in real time on :class:`RealClock` and as fast as the CPU allows on
:class:`VirtualClock`, which jumps straight to the earliest pending deadline whenever every
sleeper is waiting on it.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import math
import time
from collections.abc import Callable
from typing import Any, Protocol


class Clock(Protocol):
    """A source of time for the step generator, modules and timers."""

    def now_s(self) -> float:
        """Current time in seconds on this clock."""
        ...

    async def sleep_until(self, deadline_s: float) -> None:
        """Return once ``now_s() >= deadline_s`` (at once if it already is)."""
        ...

    def call_at(self, deadline_s: float, callback: Callable[[], None]) -> Any:
        """Call ``callback()`` once ``now_s() >= deadline_s``; the result's ``cancel()``
        calls it off."""
        ...


class RealClock:
    """Monotonic time, the same the event loop uses. Sleeps may overshoot; callers catch up."""

    def now_s(self) -> float:
        return time.monotonic()

    async def sleep_until(self, deadline_s: float) -> None:
        delay_s = deadline_s - self.now_s()
        if delay_s > 0:
            await asyncio.sleep(delay_s)

    def call_at(self, deadline_s: float, callback: Callable[[], None]) -> asyncio.TimerHandle:
        """``callback()`` from the event loop once ``deadline_s`` has come (a timer: one turn
        of the loop, where an awaited sleep takes two)."""
        loop = asyncio.get_running_loop()
        return loop.call_later(max(0.0, deadline_s - self.now_s()), callback)

    async def sleep(self, duration_s: float) -> None:
        await self.sleep_until(self.now_s() + duration_s)


class VirtualClock:
    """Time that advances only when every sleeper is waiting.

    A background driver task (owned by :meth:`run`) repeatedly lets the event loop settle, then
    jumps time to the earliest deadline and wakes its sleepers. I/O still works: while any task is
    runnable, time stands still.
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._now_s = start_s
        self._sleepers: list[tuple[float, int, asyncio.Future[None]]] = []
        self._counter = itertools.count()
        self._wakeup = asyncio.Event()

    def now_s(self) -> float:
        return self._now_s

    async def sleep_until(self, deadline_s: float) -> None:
        if deadline_s <= self._now_s:
            await asyncio.sleep(0)
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (deadline_s, next(self._counter), future))
        self._wakeup.set()
        await future

    async def sleep(self, duration_s: float) -> None:
        await self.sleep_until(self._now_s + duration_s)

    def call_at(self, deadline_s: float, callback: Callable[[], None]) -> asyncio.Future[None]:
        """``callback()`` once time reaches ``deadline_s`` (cancel the returned future to
        call it off)."""
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (deadline_s, next(self._counter), future))
        self._wakeup.set()
        future.add_done_callback(lambda done: None if done.cancelled() else callback())
        return future

    def advance_to(self, time_s: float) -> None:
        """Jump to ``time_s`` and wake every sleeper whose deadline has come."""
        self._now_s = max(self._now_s, time_s)
        while self._sleepers and self._sleepers[0][0] <= self._now_s:
            _, _, future = heapq.heappop(self._sleepers)
            if not future.done():
                future.set_result(None)

    async def run(self, settle_rounds: int = 4) -> None:
        """Drive time forever: let runnable tasks finish, then jump to the next deadline."""
        while True:
            for _ in range(settle_rounds):
                await asyncio.sleep(0)
            while self._sleepers and self._sleepers[0][2].done():
                heapq.heappop(self._sleepers)
            if not self._sleepers:
                self._wakeup.clear()
                await self._wakeup.wait()
                continue
            self.advance_to(self._sleepers[0][0])


def on_grid_s(now_s: float, period_s: float) -> float:
    """The first whole multiple of ``period_s`` after ``now_s`` (monotonic seconds): periodic
    wake-ups on this grid coincide (one wake-up of the process serves them all)."""
    return (math.floor(now_s / period_s) + 1) * period_s
