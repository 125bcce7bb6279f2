"""The real-time budget: no single step of the motion path does unbounded work.

Counted in deterministic units (objects, blocks), never in time:

* garbage collection while a job streams: the pacer collects the youngest generation on time,
  so no collection ever goes over the planner's whole window of objects;
* the planning path while a 20,000 segments/s raster streams over TCP and the step generator
  falls 50 ms behind: blocks synced per call, planned per ``plan()`` and gone through per
  step-generator call are bounded, whatever the window holds;
* and the bounded calls change nothing: a plan made ``plan_blocks`` at a time equals the plan
  of the whole window, and a late tick caught up in slices emits the same steps;
* ``motiond estimate`` runs with no garbage collection (each full one re-scanned the whole
  job's lines) and leaves the collector as it found it.
"""

from __future__ import annotations

import asyncio
import gc
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings

from server.backends.sim import SimBackend
from server.cli import main
from server.cli import offline as commands
from server.machine.parts import planner_settings
from server.motion.moves import Move, MoveKind
from server.motion.planner import Planner, PlannerSettings
from server.motion.stepgen import StepGenerator
from server.offline.stats import JobStats
from server.runtime.clock import RealClock, VirtualClock
from server.runtime.gcpacer import GcPacer
from server.transports.tcp import TcpTransport
from tests.conftest import REPO, make_config
from tests.integration.test_stepgen import POLYLINE, Quiet
from tests.support.helpers import running
from tests.support.senders import CharCountingClient, fast_axes, wait_for
from tests.unit.test_planner import append_all, machine_and_path, run

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


# -- the planning path -----------------------------------------------------------------------------
class WorkCounter:
    """Records the work of every call on the planning path, in blocks."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.synced: list[int] = []  # blocks copied into the columns per sync
        self.planned: list[int] = []  # blocks planned per plan()
        self.per_emit: list[int] = []  # blocks gone through per step-generator call
        self._done = 0
        sync, plan, emit = Planner._sync, Planner.plan, StepGenerator._emit

        def counted_sync(planner: Planner) -> None:
            columns = planner._columns
            self.synced.append(columns.tail - columns._synced)
            sync(planner)

        def counted_plan(planner: Planner) -> None:
            dirty = planner._dirty
            plan(planner)
            if dirty:
                self.planned.append(planner._planned)

        def counted_emit(stepgen: StepGenerator, now_s: float) -> None:
            done = stepgen.state.blocks_done
            self.per_emit.append(done - self._done)  # one emit ends every call
            self._done = done
            emit(stepgen, now_s)

        monkeypatch.setattr(Planner, "_sync", counted_sync)
        monkeypatch.setattr(Planner, "plan", counted_plan)
        monkeypatch.setattr(StepGenerator, "_emit", counted_emit)


class HeldClock(VirtualClock):
    """Virtual time that stands still while :attr:`held` (the lines still arrive)."""

    held = False

    def advance_to(self, time_s: float) -> None:
        if not self.held:
            super().advance_to(time_s)


async def test_at_20k_segments_per_s_no_call_of_the_planning_path_works_through_the_window(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The window holds 4,096 blocks; a tick 50 ms late is 1,000 blocks behind. Each call
    still syncs at most sync_blocks, plans at most plan_blocks and steps through at most
    max_blocks_per_call blocks (one more when a budget ends on a block boundary).

    On virtual time the machine moves whenever every task waits, so the client keeps 64 KB in
    flight (not 128 bytes) and time is held once the motion has begun, until the lines have
    filled the window (a race otherwise: 1 run in 3 to 6 never filled it)."""
    work = WorkCounter(monkeypatch)
    segments = 12_000
    config = make_config(axes=fast_axes(travel_mm=5000, rate_mm_s=10000, accel_mm_s2=50000))
    clock = HeldClock()
    async with running(config, clock, [TcpTransport]) as app:
        machine = app.kernel.machine
        stepgen, planner = machine.stepgen, machine.planner
        port = app.transports[0].port  # type: ignore[attr-defined]
        client = await CharCountingClient.connect("127.0.0.1", port, window=65536)
        streaming = asyncio.create_task(client.stream(raster_lines(segments)))
        await wait_for(lambda: stepgen.state.moving, 30.0, "the motion begun")
        clock.held = True  # time stands while the lines fill the window (else a race)
        # thousands of blocks (the window stops taking them at 3,900 to 4,096 of these, by
        # the time they plan), three times what a tick 50 ms late is behind
        await wait_for(lambda: len(planner) >= 3000, 30.0, "a full window in motion")
        clock.held = False
        clock.advance_to(clock.now_s() + 0.05)  # the step generator wakes 50 ms late
        result = await asyncio.wait_for(streaming, 60)
        await asyncio.wait_for(machine.wait_idle(), 60)
        await client.close()
    assert result.replies == ["ok"] * (segments + 2)
    assert stepgen.state.position_mm == (segments * 0.1, 0.0, 0.0)
    assert machine.backend.steps == [segments * 8, 0, 0]
    assert max(work.synced) <= planner.settings.sync_blocks
    assert max(work.planned) <= planner.settings.plan_blocks
    assert max(work.per_emit) <= stepgen.max_blocks_per_call + 1
    assert sum(work.per_emit) >= segments  # every block went through a counted call


@settings(max_examples=100, deadline=None)
@given(machine_and_path())
def test_planning_a_few_blocks_at_a_time_gives_the_plan_of_the_whole_window(
    case: tuple[PlannerSettings, list[Move], list[int]],
) -> None:
    machine, moves, dwells = case
    blocks = []
    for plan_blocks in (1, 3, 10**9):
        planner = Planner(replace(machine, plan_blocks=plan_blocks), (0.0, 0.0))
        append_all(planner, moves, dwells)
        blocks.append(run(planner))
    whole = blocks[-1]
    for few in blocks[:-1]:
        assert len(few) == len(whole)
        for one, other in zip(few, whole, strict=True):
            speeds = (one.entry_mm_s, one.cruise_mm_s, one.exit_mm_s, one.duration_s)
            expected = (other.entry_mm_s, other.cruise_mm_s, other.exit_mm_s, other.duration_s)
            assert all(math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)
                       for a, b in zip(speeds, expected, strict=True))


def sliced_run(max_blocks_per_call: int) -> tuple[SimBackend, StepGenerator, list[bool]]:
    core = make_config().core
    planner = Planner(planner_settings(core), (0.0, 0.0, 0.0))
    steps_per_mm = tuple(axis.steps_per_mm for axis in core.axes.values())
    backend = SimBackend(core.axis_names, steps_per_mm)
    stepgen = StepGenerator(planner, backend, steps_per_mm, Quiet(),
                            max_blocks_per_call=max_blocks_per_call)
    for k in range(1, 401):  # 0.05 mm segments, then the polyline
        planner.append(Move((0.05 * k, 0.0, 0.0), 80.0, MoveKind.FEED))
    for point in POLYLINE:
        planner.append(Move(point, 80.0, MoveKind.FEED))
    stepgen.request_start()
    stepgen.advance(0.0)
    moving, now_s = [], 0.0
    while not stepgen.idle:
        now_s += 0.05  # every tick 50 ms late
        while not stepgen.advance(now_s):
            moving.append(stepgen.state.moving)
    return backend, stepgen, moving


def test_a_late_tick_caught_up_in_slices_emits_the_same_steps_and_keeps_moving() -> None:
    sliced_backend, sliced, moving = sliced_run(max_blocks_per_call=3)
    whole_backend, whole, _ = sliced_run(max_blocks_per_call=10**9)
    assert moving and all(moving)  # between slices motion is still under way
    assert sliced_backend.steps == whole_backend.steps == [2000, 2000, 800]
    assert sliced.state.position_mm == whole.state.position_mm == POLYLINE[-1]
    assert math.isclose(sliced.state.motion_time_s, whole.state.motion_time_s, rel_tol=1e-12)
    reference = {round(row[0], 9): row[1:4] for row in whole_backend.history}
    for row in sliced_backend.history:
        expected = reference.get(round(row[0], 9))
        if expected is not None:  # the times both emitted at: the same position
            assert all(abs(a - b) < 1e-9 for a, b in zip(row[1:4], expected, strict=True))


# -- motiond estimate ------------------------------------------------------------------------------
def test_motiond_estimate_runs_without_garbage_collection_and_restores_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    job = tmp_path / "raster.nc"
    job.write_text("\n".join(raster_lines(30_000)) + "\n")
    collections: list[int] = []
    estimate = commands.estimate  # as the command calls it

    def count(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            collections.append(info["generation"])

    def counted_estimate(*args: Any, **kwargs: Any) -> JobStats:
        gc.callbacks.append(count)
        try:
            return estimate(*args, **kwargs)
        finally:
            gc.callbacks.remove(count)

    monkeypatch.setattr(commands, "estimate", counted_estimate)
    frozen, enabled = gc.get_freeze_count(), gc.isenabled()
    assert main(["estimate", str(job), "--json", "--no-limits"]) == 0
    assert collections == []  # 200-250 collections (a few full ones) otherwise
    assert gc.isenabled() == enabled
    # nothing frozen: the permanent generation did not grow by the job's objects (it may shrink:
    # objects an earlier server froze can be freed by reference counting at any time)
    assert gc.get_freeze_count() <= frozen
    assert json.loads(capsys.readouterr().out)["moves"] == 30_000
