"""The virtual clock runs long scenarios in milliseconds; the real clock follows loop time."""

from __future__ import annotations

import asyncio
import time

from server.runtime.clock import RealClock, VirtualClock


async def test_virtual_clock_runs_a_60_second_scenario_in_well_under_a_second() -> None:
    clock = VirtualClock()
    driver = asyncio.create_task(clock.run())
    ticks: list[float] = []

    async def ticker() -> None:
        for _ in range(600):
            await clock.sleep(0.1)
            ticks.append(clock.now_s())

    started = time.perf_counter()
    await asyncio.wait_for(ticker(), timeout=5)
    wall_s = time.perf_counter() - started
    driver.cancel()
    assert abs(ticks[-1] - 60.0) < 1e-6
    assert wall_s < 1.0


async def test_virtual_clock_wakes_sleepers_in_deadline_order() -> None:
    clock = VirtualClock()
    driver = asyncio.create_task(clock.run())
    woke: list[str] = []

    async def sleeper(name: str, at_s: float) -> None:
        await clock.sleep_until(at_s)
        woke.append(name)

    await asyncio.gather(sleeper("late", 5), sleeper("early", 1), sleeper("mid", 3))
    driver.cancel()
    assert woke == ["early", "mid", "late"]
    assert clock.now_s() == 5


async def test_real_clock_sleeps_until_the_deadline() -> None:
    clock = RealClock()
    deadline = clock.now_s() + 0.02
    await clock.sleep_until(deadline)
    assert clock.now_s() >= deadline
