"""What the API socket may take from the server: event-loop time and memory for scripts.

Every connection of ``[klippy_api]`` draws on one :class:`LoopBudget`, so that however many
clients flood the socket, the step generator's ticks and every other sender find the loop free
within about ``burst_s`` (DESIGN.md: nothing blocks the loop for more than ~2 ms). Work is
done in small pieces, each after ``await budget.turn()``. The pieces that run in one turn of
the event loop, whichever connection they serve, form a *stretch*. A stretch ends when the
loop turns (its timers and I/O had their turn: nothing to catch up), or at the first
``turn`` after it has lasted ``burst_s``: then no API work runs for ``(1 - share) / share``
times its length. A flood thus holds the loop at most ``burst_s`` plus one piece at
a time and gets about ``share`` of it while it works without pause; a quiet client never
waits.

:class:`ByteBudget` bounds what all connections' waiting scripts hold together.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

BURST_S = 0.002
SHARE = 0.5


class LoopBudget:
    """Stretches of API work of at most ``burst_s``, and at most ``share`` of the time
    (``clock``: seconds, ``time.perf_counter``)."""

    def __init__(self, burst_s: float = BURST_S, share: float = SHARE,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.burst_s, self.share, self._clock = burst_s, share, clock
        self._stretch = 0  # counts stretches, so that a late end of an old one is ignored
        self._start_s: float | None = None  # the current stretch began (None: none runs)
        self._resume_s = 0.0  # no stretch begins before this

    def may_work(self) -> bool:
        """Whether a piece of work may run now (it then belongs to the current stretch,
        begun if none runs); sans I/O: :meth:`turn` waits on it."""
        now_s = self._clock()
        if self._start_s is None:
            if now_s < self._resume_s:
                return False
            self._begin(now_s)
            return True
        ran_s = now_s - self._start_s
        if ran_s < self.burst_s:
            return True
        self._resume_s = now_s + ran_s * (1.0 - self.share) / self.share
        self._start_s = None
        return False

    def end_stretch(self, stretch: int) -> None:
        """The loop turned (it ran its timers and I/O since the stretch began): stretch
        number ``stretch``, if it still runs, ends, and the next may begin at once."""
        if stretch == self._stretch:
            self._start_s = None

    def wait_s(self) -> float:
        """How long until a stretch may begin (0 when it may now)."""
        return max(0.0, self._resume_s - self._clock())

    async def turn(self) -> None:
        """Return once a piece of work may run (at once when it may)."""
        while True:
            if self.may_work():
                return
            await asyncio.sleep(max(self.wait_s(), 1e-4))

    def _begin(self, now_s: float) -> None:
        self._stretch += 1
        self._start_s = now_s
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            return  # (pure tests call end_stretch themselves)
        loop.call_soon(self.end_stretch, self._stretch)  # at the loop's next turn


class ByteBudget:
    """Bytes shared by every connection's waiting scripts: taken on arrival, given back when
    a script ends or its connection goes."""

    def __init__(self, limit_bytes: int) -> None:
        self.limit_bytes = limit_bytes
        self.used_bytes = 0

    def take(self, size_bytes: int) -> bool:
        """Reserve ``size_bytes``; False (nothing reserved) when they do not fit."""
        if self.used_bytes + size_bytes > self.limit_bytes:
            return False
        self.used_bytes += size_bytes
        return True

    def give(self, size_bytes: int) -> None:
        self.used_bytes = max(0, self.used_bytes - size_bytes)
