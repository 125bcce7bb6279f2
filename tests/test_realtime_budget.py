"""The real-time budget: no single step of the motion path does unbounded work.

Counted in deterministic units (objects, blocks), never in time:

* garbage collection while a job streams: the pacer collects the youngest generation on time,
  so no collection ever goes over the planner's whole window of objects;
"""

from __future__ import annotations

import asyncio
import gc
import json
import sys
from pathlib import Path

from server.clock import RealClock
from server.gcpacer import GcPacer
from server.transports.tcp import TcpTransport
from tests.conftest import REPO, make_config
from tests.helpers import running
from tests.senders import fast_axes

STREAM_CLIENT = REPO / "benchmarks" / "stream_client.py"


class FakeCollector:
    """Records what the pacer asks of the garbage collector."""

    def __init__(self) -> None:
        self.enabled = True
        self.collected: list[int] = []

    def collect(self, generation: int = 2) -> int:
        self.collected.append(generation)
        return 0

    def isenabled(self) -> bool:
        return self.enabled

    def enable(self) -> None:
        self.enabled = True

    def disable(self) -> None:
        self.enabled = False


def raster_lines(segments: int) -> list[str]:
    """0.1 mm laser segments at 2,000 mm/s (20,000 segments/s), S alternating."""
    lines = ["G21 G90 M4 S0", "G1 X0.1 S100 F120000"]
    lines += [f"X{i * 0.1:.1f} S{100 + 800 * (i % 2)}" for i in range(2, segments + 1)]
    return lines + ["M5"]


# -- garbage collection ----------------------------------------------------------------------------
def test_the_gc_pacer_collects_the_young_generation_on_time_only_while_motion_is_queued() -> None:
    collector, busy = FakeCollector(), [False]
    tick_s = 1 / 1024  # about 1 ms, exact in binary
    pacer = GcPacer(lambda: busy[0], young_period_s=2 * tick_s, old_period_s=256 * tick_s,
                    collector=collector)
    pacer.step(0.0)
    assert collector.enabled and collector.collected == []  # idle: the interpreter's own GC
    busy[0] = True
    for tick in range(1, 1025):  # one second of wake-ups while motion runs
        pacer.step(tick * tick_s)
        assert not collector.enabled
    assert collector.collected.count(0) == 512  # every other wake-up
    assert collector.collected.count(1) == 3  # once per old_period_s after pacing began
    busy[0] = False
    pacer.step(1025 * tick_s)
    assert collector.enabled and not pacer.pacing


def test_the_gc_pacer_gives_collection_back_as_it_found_it() -> None:
    collector = FakeCollector()
    collector.enabled = False  # someone else turned it off
    pacer = GcPacer(lambda: True, collector=collector)
    pacer.step(0.0)
    pacer.close()
    pacer.close()
    assert not collector.enabled and not pacer.pacing


async def test_streaming_a_raster_never_lets_the_young_generation_fill_with_the_window(
    tmp_path: Path,
) -> None:
    """Each line leaves a few objects in the planner's window and popping frees as many older
    ones, so CPython's allocation count hardly moves and its young generation used to fill
    with the whole window (over 20,000 objects here) before a collection went over them all.
    The client is another process: its allocations must not trigger collections here."""
    job = tmp_path / "raster.nc"
    job.write_text("\n".join(raster_lines(10_000)) + "\n")
    config = make_config(axes=fast_axes(travel_mm=5000, rate_mm_s=10000, accel_mm_s2=50000))
    young_sizes: list[int] = []
    full_collections = 0

    def watch(phase: str, info: dict[str, int]) -> None:
        nonlocal full_collections
        if phase == "start":
            young_sizes.append(len(gc.get_objects(generation=0)))
            full_collections += info["generation"] == 2

    async with running(config, RealClock(), [TcpTransport]) as app:
        port = app.transports[0].port  # type: ignore[attr-defined]
        gc.callbacks.append(watch)
        try:
            client = await asyncio.create_subprocess_exec(
                sys.executable, str(STREAM_CLIENT), str(port), str(job), "--banner",
                stdout=asyncio.subprocess.PIPE)
            stdout, _ = await asyncio.wait_for(client.communicate(), 60)
            await asyncio.wait_for(app.kernel.machine.wait_idle(), 60)
        finally:
            gc.callbacks.remove(watch)
    assert json.loads(stdout.decode().splitlines()[-1])["errors"] == 0
    assert app.kernel.machine.stepgen.state.position_mm[0] == 1000.0
    assert young_sizes, "the pacer collected the young generation while motion ran"
    assert max(young_sizes) <= 4000, f"a collection went over {max(young_sizes)} young objects"
    assert full_collections == 0
