"""Garbage collection paced by time while motion is queued, so no collection stalls the loop.

CPython starts a young collection when its count of allocations minus deallocations passes
700. While a job streams, each line allocates a few objects that then wait in the planner's
window, and popping a block frees as many older ones: the count hardly moves while the
youngest generation fills up with the whole window (25,000 objects at 4,096 blocks), so the
collection that finally comes examines all of them and stalls the loop for 2-8 ms, and the
older generations then go over the same objects again.

:class:`GcPacer` removes that: while motion is queued it turns automatic collection off and
collects the youngest generation every ``young_period_s`` instead, when it holds only what a
few milliseconds allocated (tens of microseconds of work). The older generations are left
alone while motion lasts: what survives a young collection is almost only the window's
blocks, which reference counting frees when they are popped; the streaming path makes no
reference cycles (the streaming benchmark counts the collections). Cyclic garbage that lives
through a young collection waits for the machine to stop, when automatic collection is back
on and the window is empty; a stream longer than ``old_period_s`` gets one collection of the
middle generation per period as a bound.
"""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import Protocol


class Collector(Protocol):
    """The part of the :mod:`gc` module the pacer uses (a fake in tests)."""

    def collect(self, generation: int = 2) -> int: ...

    def isenabled(self) -> bool: ...

    def enable(self) -> None: ...

    def disable(self) -> None: ...


class GcPacer:
    """See the module docstring. :meth:`step` is called about every millisecond (by the
    kernel's :class:`~server.kernel.kernel.LoopMonitor`) with monotonic seconds; ``busy()`` says
    whether motion is queued or running."""

    def __init__(
        self,
        busy: Callable[[], bool],
        *,
        young_period_s: float = 0.002,
        old_period_s: float = 60.0,
        collector: Collector = gc,
    ) -> None:
        self.busy = busy
        self.young_period_s = young_period_s
        self.old_period_s = old_period_s
        self.collector = collector
        self.pacing = False
        self.young_collections = self.old_collections = 0
        self._was_enabled = False
        self._next_young_s = self._next_old_s = 0.0

    def step(self, now_s: float) -> None:
        """Start or stop pacing with motion; collect what is due."""
        if not self.busy():
            if self.pacing:
                self.close()
            return
        if not self.pacing:
            self._start(now_s)
        if now_s >= self._next_young_s:
            self._next_young_s = max(self._next_young_s + self.young_period_s, now_s)
            self.collector.collect(0)
            self.young_collections += 1
        if now_s >= self._next_old_s:
            self._next_old_s = max(self._next_old_s + self.old_period_s, now_s)
            self.collector.collect(1)
            self.old_collections += 1

    def close(self) -> None:
        """Give collection back to the interpreter as it was (repeatable)."""
        if self.pacing:
            self.pacing = False
            if self._was_enabled:
                self.collector.enable()

    def _start(self, now_s: float) -> None:
        self.pacing = True
        self._was_enabled = self.collector.isenabled()
        self.collector.disable()
        self._next_young_s = now_s
        self._next_old_s = now_s + self.old_period_s
