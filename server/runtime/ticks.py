"""The step generator's task: ticks on the kernel's clock, as timer callbacks.

Each tick is a timer callback on the clock (:meth:`~server.runtime.clock.RealClock.call_at`):
one turn of the event loop, where an awaited sleep takes two (the timer's, then the task's
step; ~80 µs of CPU more per tick on this machine). A tick late by more blocks than one call
goes through (:meth:`StepGenerator.advance`) hands the rest to the task, which slices it with
other callbacks in between. While the generator :attr:`~StepGenerator.can_sleep`, the task
waits for work instead of ticking (an idle server costs no CPU), and the timeline resumes at
the wake-up. A :class:`TickWatch` (the kernel's loop monitor) is told each tick's lateness and
when the ticks stop. A tick that raises (a failing backend) is reported to ``on_fault``, which
must stop motion; the ticks go on, so the server stays up and answers.

The ticks come every ``tick_s``, or as :meth:`~StepGenerator.next_tick_s` says after each one
(a backend that times its own steps is sampled only when it needs to be: each wake-up of the
process costs CPU). Between ticks, :attr:`~StepGenerator.hurry` brings the next one forward
(a hold, a halt, input while nothing runs); during a tick it is not needed (the next deadline
is decided after the tick, from the state it left).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from server.motion.stepgen import StepGenerator


class Cancellable(Protocol):
    def cancel(self) -> Any: ...


class TickClock(Protocol):
    """The time a step generator runs on (the runtime's RealClock or VirtualClock), seconds."""

    def now_s(self) -> float: ...

    async def sleep_until(self, time_s: float) -> None: ...

    def call_at(self, time_s: float, callback: Callable[[], None]) -> Cancellable: ...


class TickWatch(Protocol):
    """What watches the ticks on real time (the kernel's loop monitor): told how late each
    tick woke (seconds after its deadline) and when the ticks stop."""

    def tick(self, late_s: float) -> None: ...

    def rest(self) -> None: ...


async def run_ticks(
    generator: StepGenerator,
    clock: TickClock,
    after_tick: Callable[[], None] = lambda: None,
    on_fault: Callable[[Exception], None] | None = None,
    give_turn: Callable[[], Awaitable[None]] | None = None,
    wait_for_work: Callable[[], Awaitable[None]] | None = None,
    watch: TickWatch | None = None,
) -> None:
    """Tick ``generator`` every ``tick_s`` on ``clock`` forever (see the module docstring).
    ``give_turn`` lets the loop run other callbacks in the middle of a late tick (the runtime
    passes ``asyncio.sleep(0)``; default: a zero sleep on ``clock``). ``wait_for_work`` returns
    once the generator's ``wake`` has been called (default: tick always)."""
    next_s = clock.now_s()
    generator.resume_at(next_s)
    try:
        while True:
            if wait_for_work is not None and generator.can_sleep:
                if watch is not None:
                    watch.rest()
                await wait_for_work()
                next_s = clock.now_s()
                generator.resume_at(next_s)  # no catching up on the time slept
            ticks = _Ticks(generator, clock, next_s, after_tick, on_fault, watch,
                           sleeps=wait_for_work is not None)
            try:
                late_s = await ticks.done
            finally:
                ticks.stop()
            next_s = ticks.next_s
            if late_s is None:
                continue
            while True:  # the rest of a late tick, other callbacks run in between
                after_tick()
                await (give_turn() if give_turn is not None else clock.sleep_until(late_s))
                if _guarded(generator.advance, late_s, on_fault):
                    break
            after_tick()
    finally:
        if watch is not None:
            watch.rest()


def _guarded(advance: Callable[[float], bool], now_s: float,
             on_fault: Callable[[Exception], None] | None) -> bool:
    """``advance(now_s)``, a failure reported to ``on_fault`` (which stops motion)."""
    try:
        return advance(now_s)
    except Exception as exc:
        if on_fault is None:
            raise
        on_fault(exc)
        return True


class _Ticks:
    """The ticks as timer callbacks on ``clock`` until the generator may sleep (``done`` gets
    None; only if ``sleeps``) or a tick runs late by more blocks than one call goes through
    (``done`` gets its time: the task slices the rest)."""

    def __init__(self, generator: StepGenerator, clock: TickClock, last_s: float,
                 after_tick: Callable[[], None], on_fault: Callable[[Exception], None] | None,
                 watch: TickWatch | None, *, sleeps: bool) -> None:
        self.generator, self.clock, self.after_tick = generator, clock, after_tick
        self.on_fault, self.watch, self.sleeps = on_fault, watch, sleeps
        self.done: asyncio.Future[float | None] = asyncio.get_running_loop().create_future()
        self.next_s = generator.next_tick_s(last_s, last_s)
        self._handle = clock.call_at(self.next_s, self._fire)
        generator.hurry = self.hurry

    def stop(self) -> None:
        self._handle.cancel()
        self.generator.hurry = _no_hurry

    def hurry(self, within_s: float) -> None:
        """The next tick within ``within_s`` from now, if it was due more than a ``tick_s``
        from now (sparse ticks; ticks a ``tick_s`` apart keep their grid)."""
        now_s = self.clock.now_s()
        due_s = now_s + within_s
        if self.next_s > now_s + self.generator.tick_s and not self.done.done():
            self._handle.cancel()
            self.next_s = due_s
            self._handle = self.clock.call_at(due_s, self._fire)

    def _fire(self) -> None:
        generator = self.generator
        generator.hurry = _no_hurry  # the next deadline is decided after this tick
        try:
            now_s = self.clock.now_s()
            if self.watch is not None:
                self.watch.tick(now_s - self.next_s)
            if now_s - self.next_s > generator.tick_s:  # late: this tick goes to now, so the
                self.next_s = now_s  # deadlines it passed are not replayed one after another
            if not _guarded(generator.advance, now_s, self.on_fault):
                self.done.set_result(now_s)
                return
            self.after_tick()
            if self.sleeps and generator.can_sleep:
                self.done.set_result(None)
                return
            self.next_s = generator.next_tick_s(self.next_s, now_s)
            self._handle = self.clock.call_at(self.next_s, self._fire)
            generator.hurry = self.hurry
        except Exception as exc:  # noqa: BLE001 - the task raises it (no on_fault given)
            if not self.done.done():
                self.done.set_exception(exc)


def _no_hurry(within_s: float) -> None:
    """No tick is scheduled (none to bring forward) or one runs now."""
