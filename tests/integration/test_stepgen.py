"""The step generator: exact steps, jitter-free paths, hold/resume, reset, jog cancel, overrides."""

from __future__ import annotations

import math
import random
from collections.abc import Callable

import pytest

from server.backends.sim import SimBackend
from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.gcode.parser import parse_line
from server.machine.parts import interpreter_settings, planner_settings
from server.motion.motion_state import HoldState
from server.motion.moves import Move, MoveKind
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from server.offline.estimate import estimate, execute, iterate_blocks
from server.offline.stats import JobStats
from server.runtime.events import MachineState
from tests.conftest import CORPUS, make_config
from tests.support.helpers import running, submit_all


class Quiet:
    def __init__(self) -> None:
        self.actions: list[str] = []
        self.idle = 0

    def on_action(self, action) -> None:  # type: ignore[no-untyped-def]
        self.actions.append(action.name)

    def on_idle(self) -> None:
        self.idle += 1

    def on_hold_stopped(self) -> None:
        pass


def core_config() -> CoreConfig:
    return make_config().core


def generator(core: CoreConfig) -> tuple[StepGenerator, SimBackend, Planner]:
    planner = Planner(planner_settings(core), (0.0, 0.0, 0.0))
    steps_per_mm = tuple(a.steps_per_mm for a in core.axes.values())
    backend = SimBackend(core.axis_names, steps_per_mm)
    return StepGenerator(planner, backend, steps_per_mm, Quiet(), tick_hz=1000), backend, planner


def feed(planner: Planner, points: list[tuple[float, float, float]], feed_mm_s: float) -> None:
    for point in points:
        planner.append(Move(point, feed_mm_s, MoveKind.FEED))


def run_until_idle(stepgen: StepGenerator, times: list[float] | None = None) -> float:
    stepgen.request_start()
    now = 0.0
    stepgen.tick(now)
    for index in range(10**7):
        now = times[index] if times else now + 0.001
        stepgen.tick(now)
        if stepgen.idle:
            return now
    raise AssertionError("never idle")


POLYLINE = [(10.0, 0.0, 0.0), (10.0, 7.3, 0.0), (3.1, 12.9, -1.0), (0.0, 0.0, 0.0),
            (25.0, 25.0, 2.0)]


def test_emitted_steps_always_sum_to_the_commanded_position() -> None:
    stepgen, backend, planner = generator(core_config())
    feed(planner, POLYLINE, 80.0)
    run_until_idle(stepgen)
    assert backend.steps == [2000, 2000, 800]
    assert stepgen.state.position_mm == (25.0, 25.0, 2.0)


def test_late_ticks_change_neither_the_path_nor_the_timing_nor_the_steps() -> None:
    smooth, smooth_backend, smooth_planner = generator(core_config())
    feed(smooth_planner, POLYLINE, 80.0)
    end_smooth = run_until_idle(smooth)
    rng = random.Random(7)
    times, now = [], 0.0
    while now < end_smooth + 1:
        now += 0.001 + rng.choice([0.0, 0.0, 0.0005, 0.003])
        times.append(now)
    jittery, jitter_backend, jitter_planner = generator(core_config())
    feed(jitter_planner, POLYLINE, 80.0)
    run_until_idle(jittery, times)
    assert jitter_backend.steps == smooth_backend.steps
    reference = {round(row[0], 6): row[1:4] for row in smooth_backend.history}
    compared = 0
    for row in jitter_backend.history:
        expected = reference.get(round(row[0], 6))
        if expected is not None:
            compared += 1
            assert all(abs(a - b) < 1e-9 for a, b in zip(row[1:4], expected, strict=True))
    assert compared > 100


class Ticker:
    """Drives a step generator at 1 kHz on a hand-held clock."""

    def __init__(self, stepgen: StepGenerator) -> None:
        self.stepgen, self.now = stepgen, 0.0
        stepgen.request_start()
        stepgen.tick(self.now)

    def until(self, done: Callable[[], bool]) -> list[float]:
        """Tick until ``done()``; the speed after each tick."""
        speeds = []
        while not done():
            self.now += 0.001
            self.stepgen.tick(self.now)
            speeds.append(self.stepgen.state.speed_mm_s)
        return speeds


def test_feed_hold_decelerates_within_the_limit_and_resume_finishes_exactly() -> None:
    stepgen, backend, planner = generator(core_config())
    feed(planner, [(100.0, 0.0, 0.0), (100.0, 100.0, 0.0)], 200.0)
    ticker = Ticker(stepgen)
    ticker.until(lambda: stepgen.state.speed_mm_s >= 150)
    stepgen.hold()
    assert stepgen.state.hold is HoldState.DECELERATING
    speeds = ticker.until(lambda: stepgen.state.hold is HoldState.STOPPED)
    accel = 3000.0
    assert all(a - b <= accel * 0.001 + 1e-9 for a, b in zip(speeds, speeds[1:], strict=False))
    stopped_at = stepgen.state.position_mm
    held_until = ticker.now + 0.2
    ticker.until(lambda: ticker.now >= held_until)  # stays put while held
    assert stepgen.state.position_mm == stopped_at
    stepgen.resume()
    ticker.until(lambda: stepgen.idle)
    assert stepgen.state.position_mm == (100.0, 100.0, 0.0)
    assert backend.steps == [8000, 8000, 0]


def test_hold_on_short_blocks_decelerates_across_block_boundaries() -> None:
    stepgen, backend, planner = generator(core_config())
    feed(planner, [(0.5 * i, 0.0, 0.0) for i in range(1, 200)], 300.0)
    ticker = Ticker(stepgen)
    ticker.until(lambda: stepgen.state.speed_mm_s >= 250)
    blocks_before = stepgen.state.blocks_done
    stepgen.hold()
    ticker.until(lambda: stepgen.state.hold is HoldState.STOPPED)
    assert stepgen.state.blocks_done > blocks_before + 5, "a 300 mm/s stop takes 15 mm"
    stepgen.resume()
    ticker.until(lambda: stepgen.idle)
    assert backend.steps == [round(99.5 * 80), 0, 0]


@pytest.mark.slow
def test_estimate_agrees_with_full_execution_on_corpus_files() -> None:
    core = make_config(machine={"soft_limits": False}).core
    for name in ("laser-vector-jsdc.gcode", "laser-engrave-tball.gcode"):
        lines = (CORPUS / name).read_text().splitlines()
        fast = estimate(lines, core)
        full = execute(lines, core)
        assert fast.error is None and fast.blocks == full.blocks
        allowed_s = 0.001 * (1 + fast.moves / 1000)
        assert abs(fast.duration_s - full.duration_s) <= allowed_s, name


@pytest.mark.slow
def test_full_execution_steps_match_the_program_end_on_the_sim_backend() -> None:
    core = make_config(machine={"soft_limits": False}).core
    backend = SimBackend(core.axis_names, [a.steps_per_mm for a in core.axes.values()])
    lines = (CORPUS / "laser-vector-jsdc.gcode").read_text().splitlines()
    execute(lines, core, backend)
    from server.gcode.interpreter import Interpreter
    from server.gcode.parser import parse_line
    from server.machine.parts import interpreter_settings

    interpreter = Interpreter(interpreter_settings(core))
    interpreter.set_position((0.0, 0.0, 0.0))
    for line in lines:
        interpreter.execute(parse_line(line))
    expected = [round(p * s) for p, s in zip(interpreter.position, backend.steps_per_mm,
                                              strict=True)]
    assert backend.steps == expected


async def test_soft_reset_mid_move_stops_at_once_keeps_the_position_and_alarms() -> None:
    async with running(make_config()) as app:
        machine = app.kernel.machine
        await submit_all(app, ["G1 X200 F3000"])
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        x_before = machine.stepgen.state.position_mm[0]
        machine.soft_reset()
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 3
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        state = machine.stepgen.state
        assert state.position_mm[0] == x_before and not state.moving
        assert machine.backend.steps[0] == round(x_before * 80)
        assert machine.interpreter.position == state.position_mm
        assert await submit_all(app, ["$X", "G90 G0 X0"]) == [[], []]
        await machine.wait_idle()
        assert machine.backend.steps[0] == 0


async def test_jog_cancel_decelerates_and_drops_the_remaining_jog_moves() -> None:
    async with running(make_config()) as app:
        machine = app.kernel.machine
        await submit_all(app, ["$J=G91 X100 F6000", "$J=G91 X100 F6000"])
        await app.clock.sleep(0.3)  # type: ignore[attr-defined]
        assert app.kernel.state is MachineState.JOG
        machine.cancel_jog()
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        assert app.kernel.state is MachineState.IDLE
        x = machine.stepgen.state.position_mm[0]
        assert 10 < x < 100
        assert len(machine.planner) == 0
        assert machine.interpreter.position[0] == pytest.approx(x)


async def test_feed_override_replans_the_queued_moves() -> None:
    async def job_time(override: int) -> float:
        async with running(make_config()) as app:
            app.kernel.machine.set_overrides(feed=override)
            start = app.clock.now_s()
            await submit_all(app, ["G1 X100 F600", "G1 X0"])
            await app.kernel.machine.wait_idle()
            return app.clock.now_s() - start

    slow, fast = await job_time(100), await job_time(200)
    assert fast == pytest.approx(slow / 2, rel=0.05)
    assert math.isclose(slow, 20.0, rel_tol=0.02)


def _block_speeds(lines: list[str], core: CoreConfig) -> list[tuple[float, ...]]:
    stats = JobStats()
    return [(block.entry_mm_s, block.cruise_mm_s, block.exit_mm_s, block.duration_s)
            for block in iterate_blocks(lines, core, stats)]


def _fast_zigzag() -> list[str]:
    """Short segments at 300 mm/s with corners: a window of a few blocks cannot reach cruise,
    so its end shapes the plan and the lazy criterion decides often."""
    lines = ["G1 F18000"]
    for k in range(1, 1500):
        lines.append(f"G1 X{0.4 * k:.3f} Y{(k % 7) * 0.3 if k % 50 else 5.0:.3f}")
    return lines


@pytest.mark.parametrize("window", ["jsdc, default window", "zigzag, 6-block window"])
def test_lazy_replanning_gives_exactly_the_plan_of_replanning_at_every_pop(
    monkeypatch: pytest.MonkeyPatch, window: str
) -> None:
    if window.startswith("jsdc"):
        core = make_config(machine={"soft_limits": False}).core
        lines = (CORPUS / "laser-vector-jsdc.gcode").read_text().splitlines()[:1200]
    else:
        planner = {"max_blocks": 6, "max_planned_s": 60.0}
        core = make_config(machine={"soft_limits": False}, planner=planner).core
        lines = _fast_zigzag()
    lazy = _block_speeds(lines, core)
    monkeypatch.setattr(Planner, "lookahead_short", lambda self: self._dirty)
    eager = _block_speeds(lines, core)
    assert len(lazy) == len(eager) > 1000
    for one, other in zip(lazy, eager, strict=True):  # equal but for rounding (a few ulps)
        assert all(math.isclose(a, b, rel_tol=1e-12, abs_tol=1e-12)
                   for a, b in zip(one, other, strict=True))


@pytest.mark.parametrize(
    "name", ["zigzag"] + sorted(p.name for p in CORPUS.iterdir() if p.suffix != ".md"))
@pytest.mark.slow
def test_estimate_in_settled_batches_sums_the_blocks_popped_one_by_one(name: str) -> None:
    if name == "zigzag":
        planner = {"max_blocks": 6, "max_planned_s": 60.0}
        core = make_config(machine={"soft_limits": False}, planner=planner).core
        lines = _fast_zigzag()
    else:
        core = make_config(machine={"soft_limits": False}).core
        lines = (CORPUS / name).read_text(errors="replace").splitlines()
    batched, single = estimate(lines, core), JobStats()
    blocks = list(iterate_blocks(lines, core, single))
    assert (batched.blocks, batched.moves, batched.lines, batched.error) == (
        len(blocks), single.moves, single.lines, single.error)
    assert (batched.bbox_min_mm, batched.bbox_max_mm) == (single.bbox_min_mm, single.bbox_max_mm)
    assert batched.max_speed_mm_s == single.max_speed_mm_s
    for field in ("duration_s", "cut_mm", "rapid_mm"):
        assert math.isclose(getattr(batched, field), getattr(single, field), rel_tol=1e-12,
                            abs_tol=1e-9), field


@pytest.mark.parametrize(
    "name, refused", [("cnc-calibration-arcs.gcode", 624), ("cnc-helical-thread.gcode", 5)])
def test_estimate_stops_at_the_first_refused_line_and_reads_no_further(
    name: str, refused: int
) -> None:
    core = make_config(machine={"soft_limits": False}).core
    lines = (CORPUS / name).read_text().splitlines()
    interpreter = Interpreter(interpreter_settings(core))
    before = sum(isinstance(output, Move)
                 for text in lines[: refused - 1]
                 for output in interpreter.execute(parse_line(text)))
    stats, single = estimate(lines, core), JobStats()
    blocks = list(iterate_blocks(lines, core, single))
    for run in (stats, single):
        assert (run.error_line, run.lines, run.moves) == (refused, refused, before)
    assert stats.blocks == len(blocks)
