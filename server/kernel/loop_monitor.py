"""The event loop's stall monitor: how late the loop wakes a sleeper, measured as it runs.

The kernel owns one (``Kernel.loop_monitor``) and exposes its worst stall in the API, so a
regression that blocks the loop shows up as a number (DESIGN.md rule 8).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from server.runtime.clock import on_grid_s
from server.runtime.gcpacer import GcPacer


class LoopMonitor:
    """Measures how late the event loop wakes a sleeper of ``period_s`` (1 ms; a step
    generator that ticks less often, less often too): the worst stall, in seconds.

    It uses monotonic time whatever the kernel's clock (not the loop's ``time()``, which uvloop
    counts in whole milliseconds), since stalls are a property of the process;
    ``worst_stall_s`` is exposed in the API and printed by the streaming benchmark.
    ``worst_cpu_stall_s`` is the worst of the same stalls counted only while this thread ran
    (``min(lateness, thread CPU time since the last wake-up)``): an upper bound on what the
    process's own work (callbacks, garbage collection) delayed the loop, without the time the
    OS gave the CPU to other processes, which is what most stalls are on a loaded machine.
    It also wakes the kernel's :class:`~server.runtime.gcpacer.GcPacer`, if any.

    While the step generator ticks on real time, the monitor rides its ticks (:meth:`tick`:
    each tick's lateness after its deadline is the sleeper's lateness, measured the same way)
    and keeps no timer of its own: every wake-up of the process costs CPU. Its own sleep runs
    only while nothing ticks (:meth:`rest`), and while ``is_quiet()`` (nothing moves, no
    command for a while) it sleeps ``quiet_period_s`` instead, so an idle server does not wake
    a thousand times a second; a stall then still shows as a late wake-up, if a coarser one.
    Its own wake-ups fall on whole multiples of the period (:func:`on_grid_s`), as the other
    periodic ones of an idle server do (the kernel's second, a Klipper MCU's clock polls): one
    wake-up of the process serves them all.
    """

    def __init__(self, period_s: float = 0.001, gc_pacer: GcPacer | None = None,
                 is_quiet: Callable[[], bool] = lambda: False,
                 quiet_period_s: float = 1.0) -> None:
        self.period_s = period_s
        self.quiet_period_s = quiet_period_s
        self.is_quiet = is_quiet
        self.gc_pacer = gc_pacer  # woken with the monitor: see server.runtime.gcpacer
        self.worst_stall_s = 0.0
        self.worst_cpu_stall_s = 0.0
        self.samples = 0  # wake-ups measured (its own and the ticks')
        self.own_samples = 0  # of which on its own timer
        self.riding = False  # the step generator's ticks feed the monitor
        self._resting = asyncio.Event()  # set by rest(): the monitor's own timer runs again
        self._cpu_before_s = time.thread_time()

    def reset(self) -> None:
        self.worst_stall_s = self.worst_cpu_stall_s = 0.0

    def tick(self, late_s: float) -> None:
        """A tick of the step generator woke ``late_s`` after its deadline (monotonic time):
        measured as the monitor's own wake-up would be; the monitor's timer rests meanwhile."""
        self.riding = True
        self._observe(max(0.0, late_s), time.monotonic())

    def rest(self) -> None:
        """The ticks stopped (the step generator sleeps, or its task ended): the monitor's own
        timer runs again."""
        if self.riding:
            self.riding = False
            self._resting.set()

    def _observe(self, late_s: float, woke_s: float) -> None:
        cpu_s = time.thread_time()
        self.samples += 1
        if late_s > self.worst_stall_s:
            self.worst_stall_s = late_s
        cpu_late_s = min(late_s, cpu_s - self._cpu_before_s)
        if cpu_late_s > self.worst_cpu_stall_s:
            self.worst_cpu_stall_s = cpu_late_s
        self._cpu_before_s = cpu_s
        if self.gc_pacer is not None:
            self.gc_pacer.step(woke_s)

    async def run(self) -> None:
        try:
            while True:
                if self.riding:
                    self._resting.clear()
                    await self._resting.wait()
                    self._cpu_before_s = time.thread_time()
                    continue
                period_s = self.quiet_period_s if self.is_quiet() else self.period_s
                due_s = on_grid_s(time.monotonic(), period_s)
                await asyncio.sleep(due_s - time.monotonic())
                if self.riding:  # the ticks took over while it slept
                    continue
                woke_s = time.monotonic()
                self.own_samples += 1
                self._observe(woke_s - due_s, woke_s)
        finally:
            if self.gc_pacer is not None:
                self.gc_pacer.close()
