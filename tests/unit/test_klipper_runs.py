"""A cruise or a ramp continued block after block (a raster's line of short segments) is one
piece that the blocks lengthen (:mod:`server.motion.pieces`): the board must get exactly what
it gets with one piece a block, to the tick, through power changes, holds and halts. Each case
runs twice through the real planner, step generator and Klipper backend, merged and block by
block (``JOIN_S`` below zero: no block ever continues a piece), and compares every message."""

from __future__ import annotations

import random
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest

from benchmarks.bench_klipper_host import Listener, OfflineBackend
from server.config_loader import build_config
from server.machine.parts import planner_settings
from server.motion import pieces as pieces_module
from server.motion.backend import Piece, PowerLaw
from server.motion.motion_state import HoldState
from server.motion.moves import Action, ActionName, Move, MoveKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from tests.unit.test_klipper_mcu_time import CLOCK_HZ, FittedMcu

TICK_S = 0.007  # not a multiple of a block's 1 ms: ticks fall inside blocks and runs
Script = dict[int, Callable[[StepGenerator], object]]


def raster(lines: int, s_at: Callable[[int, int], float] = lambda line, k: 800.0,
           segments: int = 200) -> list[Move]:
    """Lines of 200 segments of 0.1 mm along X at F6000 (laser on at ``s_at(line, k)``),
    stepping over 0.1 mm in Y with the laser off (as the rig benchmark's raster)."""
    moves, x, y = [], 10.0, 10.0
    for line in range(lines):
        direction = 1 if line % 2 == 0 else -1
        for k in range(segments):
            x = round(x + 0.1 * direction, 3)
            moves.append(Move((x, y), 100.0, MoveKind.FEED, ToolMode.CW, s_at(line, k)))
        y = round(y + 0.1, 3)
        moves.append(Move((x, y), 100.0, MoveKind.FEED, ToolMode.CW, 0.0))
    return moves


def line(s_value: float, segment_mm: float, length_mm: float = 6.0) -> list[Move]:
    """One line along X from rest to rest in segments of ``segment_mm``, laser at S."""
    moves, x = [], 10.0
    for _ in range(round(length_mm / segment_mm)):
        x = round(x + segment_mm, 4)
        moves.append(Move((x, 10.0), 100.0, MoveKind.FEED, ToolMode.CW, s_value))
    return moves


def follows_speed(move: Move, nominal_mm_s: float) -> PowerLaw | None:
    """M4: the power in proportion to the speed, S at the block's nominal speed."""
    if move.s_value <= 0.0:
        return None
    return PowerLaw(0.0, move.s_value / 1000.0 / nominal_mm_s, 1.0)


def drive(moves: list[Move | Action], merge: bool, monkeypatch: pytest.MonkeyPatch,
          script: Script | None = None, board: list[Any] | None = None,
          power_of: Callable[[Move, float], PowerLaw | None] | None = None,
          tick_s: Callable[[int], float] = lambda tick: TICK_S, fed: bool = False,
          ) -> tuple[list[tuple[str, Any]], list[Piece]]:
    """Every message the backend sends for ``moves`` (an action: the planner's, in order;
    ``script``: what to do to the step generator at which tick), and every piece the step
    generator gave it (``board``: gets where the backend says the board is, and how fast,
    and the step generator's state, after every tick). The laser's power is S (M3), or
    ``power_of``'s. ``tick_s(k)``: how long tick k is; ``fed``: the planner is given the
    moves as a sender would, a batch whenever its window has room (else all at once)."""
    monkeypatch.setattr(pieces_module, "JOIN_S", 1e-9 if merge else -1.0)
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 200, "accel_mm_s2": 2000, "max_mm": 300}
            for a in "xy"}
    pins = {"x": {"step_pin": "PB13", "dir_pin": "PB12"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2"}}
    core = build_config({"axes": axes, "planner": {"junction_deviation_mm": 0.01},
                         "backend": {"kind": "klipper", "serial": "/dev/null", "axes": pins,
                                     "outputs": {"PA8": {}}}}).core
    backend, mcu = OfflineBackend(core, record=True), FittedMcu(CLOCK_HZ)
    backend.mcu, backend.ready = mcu, True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.configure(oid, mcu.dictionary, backend.cfg.max_error_s * CLOCK_HZ)
        axis.position = 800
    backend.outputs["PA8"].oid = 2
    given: list[Piece] = []
    trajectory = backend.trajectory

    def record(piece: Piece) -> None:
        given.append(piece)
        trajectory(piece)

    backend.trajectory = record  # type: ignore[method-assign]
    planner = Planner(planner_settings(core), (10.0, 10.0))
    stepgen = StepGenerator(planner, backend, (80.0, 80.0), Listener())
    backend.follow_power("PA8", 0.001)
    stepgen.follow_power(power_of or (lambda move, nominal_mm_s: PowerLaw(move.s_value / 1000.0)
                                      if move.s_value > 0.0 else None))
    waiting = list(reversed(moves))

    def refill() -> None:  # all at once; ``fed``: a batch whenever the window has room
        while waiting and (not fed or planner.has_room() or not planner.is_full()):
            move = waiting.pop()
            if isinstance(move, Action):
                planner.append_action(move)
            else:
                planner.append(move)
            if fed and planner.is_full():
                return

    refill()
    now_s = 0.0
    stepgen.tick(now_s)
    stepgen.request_start()
    for tick in range(5000):
        if script and tick in script:
            script[tick](stepgen)
        refill()
        now_s += tick_s(tick)
        backend.now_s = mcu.link.now_s = now_s
        stepgen.tick(now_s)
        if board is not None:
            state = stepgen.state
            board.append((backend.position_at_mm(now_s), backend.speed_at_mm_s(now_s),
                          state.position_mm, state.blocks_done, state.kind,
                          state.motion_time_s, state.line_number, len(stepgen.planner)))
        if stepgen.idle and stepgen.state.hold is HoldState.NONE and not backend.ticks_when_idle:
            break
    return mcu.link.messages, given


def stepped(messages: list[tuple[str, Any]]) -> dict[int, int]:
    """Net steps per stepper oid (direction from the last set_next_step_dir)."""
    direction: dict[int, int] = {}
    net = {0: 0, 1: 0}
    for name, p in messages:
        if name == "set_next_step_dir":
            direction[p["oid"]] = 1 if p["dir"] else -1
        elif name == "queue_step":
            net[p["oid"]] += direction[p["oid"]] * p["count"]
    return net


def pwm(messages: list[tuple[str, Any]]) -> list[tuple[int, int]]:
    return [(p["clock"], p["value"]) for name, p in messages if name == "queue_pwm_out"]


def test_a_raster_line_is_one_piece_and_the_board_gets_what_block_by_block_sends(
        monkeypatch: pytest.MonkeyPatch) -> None:
    moves = raster(4)
    merged, merged_pieces = drive(moves, True, monkeypatch)
    single, single_pieces = drive(moves, False, monkeypatch)
    assert merged == single
    assert stepped(merged) == {0: 0, 1: 4 * 8}  # 4 lines there and back, 4 step-overs up
    assert len(pwm(merged)) >= 8  # on and off each line
    # a line: ramps of 25 blocks each way (2,000 mm/s² to 100 mm/s), 150 blocks of cruise;
    # one piece each (and a few for the rounding of a junction speed and the step-over)
    assert len({p.start_s for p in single_pieces}) > 4 * 200
    assert len({p.start_s for p in merged_pieces}) <= 4 * 10
    assert max(p.duration_s for p in merged_pieces) > 0.14  # a line's cruise
    ramps = [p.duration_s for p in merged_pieces if p.accel_mm_s2 and p.power is not None]
    assert max(ramps) > 0.045  # a line's ramp to 100 mm/s: 50 ms


def test_a_power_change_mid_line_lands_where_its_block_starts(
        monkeypatch: pytest.MonkeyPatch) -> None:
    moves = raster(2, lambda line, k: 400.0 if 40 <= k < 60 else 800.0)
    merged, _ = drive(moves, True, monkeypatch)
    single, _ = drive(moves, False, monkeypatch)
    assert merged == single
    levels = [value for _, value in pwm(merged)]
    assert levels[:4] == [204, 102, 204, 0]  # 80 %, 40 % over segments 40-59, 80 %, off
    clocks = [clock for clock, _ in pwm(merged)]
    # 20 segments of cruise at 100 mm/s: 20 ms at 16 MHz between the power's two changes
    assert clocks[2] - clocks[1] == pytest.approx(0.020 * CLOCK_HZ, abs=2)


@pytest.mark.parametrize("at_tick", [3, 10, 15, 23, 29])  # ramps to 0.05 s and from 0.2 s
def test_a_hold_inside_a_run_decelerates_at_once_and_resumes_as_block_by_block(
        monkeypatch: pytest.MonkeyPatch, at_tick: int) -> None:
    script: Script = {at_tick: StepGenerator.hold, at_tick + 40: StepGenerator.resume}
    merged, given = drive(raster(2), True, monkeypatch, script)
    single, _ = drive(raster(2), False, monkeypatch, dict(script))
    assert merged == single
    assert stepped(merged) == {0: 0, 1: 16}
    held_s = at_tick * TICK_S  # the tick before the hold: its deceleration starts there
    decel = [p for p in given if p.accel_mm_s2 < 0.0 and p.power is None]
    assert decel and abs(decel[0].start_s - held_s) < 1e-9
    if 8 <= at_tick <= 28:
        assert decel[0].start_mm_s == pytest.approx(100.0)  # at cruise: inside the run


@pytest.mark.parametrize("at_tick", [4, 9, 20, 30])
def test_a_halt_inside_a_run_stops_the_steps_at_once_as_block_by_block(
        monkeypatch: pytest.MonkeyPatch, at_tick: int) -> None:
    script: Script = {at_tick: StepGenerator.stop_now}
    merged, given = drive(raster(2), True, monkeypatch, script)
    single, _ = drive(raster(2), False, monkeypatch, dict(script))
    assert merged == single
    stop = [p for p in given if p.duration_s == 0.0]
    assert stop and abs(stop[0].start_s - at_tick * TICK_S) < 1e-9
    net_x = stepped(merged)[0]
    assert 0 < net_x < 0.1 * 80 * (at_tick * TICK_S * 1000) + 8  # stopped where it was


def test_a_block_with_ordered_actions_starts_a_piece_of_its_own(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """An action may time something by the trajectory (M18 waits for the pieces given, and
    the next piece to start turns the drivers on again): the run ends where it runs."""
    moves = raster(1)
    moves[100].actions = [Action(ActionName.COOLANT, {"mist": True, "flood": False})]
    merged, given = drive(moves, True, monkeypatch)
    single, _ = drive(moves, False, monkeypatch)
    assert merged == single
    cruise = {p.start_s: p.start_mm for p in given  # a flush re-tells one: same start
              if p.accel_mm_s2 == 0.0 and p.duration_s > 0.01}
    starts = list(cruise.values())  # after the ramp to 100 mm/s (2.5 mm), from the action
    assert len(starts) == 2 and starts[1] == moves[99].target_mm
    assert starts[0] == pytest.approx((12.5, 10.0))


def test_status_reads_the_board_where_block_by_block_puts_it_inside_a_run(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``?`` reports what the board executed (the pieces a lead behind), never the plan: a
    run lengthened between samples changes none of it."""
    script: Script = {15: StepGenerator.hold, 40: StepGenerator.resume}
    merged: list[Any] = []
    single: list[Any] = []
    drive(raster(2), True, monkeypatch, script, merged)
    drive(raster(2), False, monkeypatch, dict(script), single)
    assert len(merged) == len(single) > 60
    for (position, speed, *_), (expected, expected_speed, *_) in zip(merged, single,
                                                                    strict=True):
        assert position == pytest.approx(expected, abs=1e-9)
        assert speed == pytest.approx(expected_speed, abs=1e-9)
    cruising = [speed for _, speed, *_ in merged if speed == pytest.approx(100.0)]
    assert len(cruising) > 20  # the board was read inside the runs, at cruise


def test_a_line_too_short_to_cruise_ramps_up_and_down_in_two_pieces(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A 2 mm line from rest to rest: the speed peaks where a block ends (1 mm in); the ramp
    down does not continue the ramp up (another acceleration), each is one piece."""
    moves = raster(1, segments=20)[:-1]
    merged, given = drive(moves, True, monkeypatch)
    single, _ = drive(moves, False, monkeypatch)
    assert merged == single
    line = [p for p in {p.start_s: p for p in given}.values()
            if p.power is not None and p.duration_s > 1e-6][:2]
    assert [p.accel_mm_s2 > 0.0 for p in line] == [True, False]
    assert line[0].duration_s == pytest.approx(line[1].duration_s)  # 1 mm each way
    assert line[1].start_mm == pytest.approx((11.0, 10.0))


@pytest.mark.parametrize(("s_value", "segment_mm"), [(800.0, 0.1), (10.0, 0.02), (2.5, 0.02)])
def test_a_laser_following_the_speed_gets_the_same_power_along_a_merged_run(
        monkeypatch: pytest.MonkeyPatch, s_value: float, segment_mm: float) -> None:
    """M4 along a line from rest to rest: the power ramps with the speed on the 1 ms grid,
    and the board gets the same levels at the same clocks as block by block (telling the
    backend a run again, longer, is not a new piece: nothing turns off and on again where
    it started, nor replays its grid)."""
    moves = line(s_value, segment_mm)
    merged, given = drive(moves, True, monkeypatch, power_of=follows_speed)
    single, _ = drive(moves, False, monkeypatch, power_of=follows_speed)
    assert len({p.start_s for p in given}) <= 6, "the line's ramps and cruise are runs"
    levels = [value for _, value in pwm(merged)]
    assert levels == [value for _, value in pwm(single)]
    assert levels[-1] == 0 and max(levels) == round(255 * s_value / 1000.0)
    for (clock, _), (clock_single, _) in zip(pwm(merged), pwm(single), strict=True):
        # block by block, a level that rounds to 0 at a block's entry speed turns on where
        # the block starts; along a run, at the grid's next look (the laser's 1 ms sample)
        assert abs(clock - clock_single) <= 0.001 * CLOCK_HZ
    assert stepped(merged) == stepped(single) == {0: round(6.0 * 80), 1: 0}


@pytest.mark.parametrize("at_tick", [3, 6, 29])  # inside the ramp up, at its end, ramping down
def test_a_hold_inside_a_run_with_the_power_following_the_speed_is_as_block_by_block(
        monkeypatch: pytest.MonkeyPatch, at_tick: int) -> None:
    script: Script = {at_tick: StepGenerator.hold, at_tick + 40: StepGenerator.resume}
    merged, _ = drive(raster(2), True, monkeypatch, dict(script), power_of=follows_speed)
    single, _ = drive(raster(2), False, monkeypatch, dict(script), power_of=follows_speed)
    assert pwm(merged) == pwm(single)
    assert merged == single


def test_a_run_is_merged_however_long_the_host_has_been_up(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The clock counts seconds since boot: after a year its float's last place is over 1 ns,
    and the blocks of a run still continue it."""
    monkeypatch.setattr(pieces_module, "JOIN_S", 1e-9)
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 200, "accel_mm_s2": 2000, "max_mm": 300}
            for a in "xy"}
    core = build_config({"axes": axes}).core
    given: list[Piece] = []
    backend = SimpleNamespace(trajectory=given.append)
    reporter = pieces_module.PieceReporter(backend)  # type: ignore[arg-type]
    planner = Planner(planner_settings(core), (10.0, 10.0))
    for move in line(800.0, 0.1, 20.0):
        planner.append(move)
    up_s, elapsed_s = 3.2e7, 0.0  # a year; each block's start as the step generator's
    while (block := planner.pop()) is not None:  # (a tick's time less what is left of it)
        reporter.block(up_s + elapsed_s, block)
        elapsed_s += block.duration_s
    reporter.flush()
    assert len({piece.start_s for piece in given}) <= 3  # ramp up, cruise, ramp down


def one_at_a_time(self: StepGenerator, now_s: float, left_s: float,
                  budget: int) -> tuple[float, int]:
    """``StepGenerator._lengthen`` taking no block: each goes through the loop, one by one."""
    return left_s, budget


def random_job(seed: int) -> list[Move | Action]:
    """Lines of short segments (odd seeds: of random lengths; even: all 0.05 mm, 0.5 ms at
    100 mm/s), S changing now and then (back to the same value, too), an action or a dwell
    here and there, a corner, a rapid, a line along Y, a line bent slightly here and there
    (at full speed: only the direction tells its blocks apart)."""
    rng = random.Random(seed)
    job: list[Move | Action] = []
    x, y, s_value, feed_mm_s = 10.0, 10.0, 800.0, 100.0
    for line in range(6):
        along_y = line == 3
        direction = 1 if line % 2 == 0 else -1
        for _ in range(rng.randrange(60, 220) if seed % 2 else rng.randrange(300, 500)):
            step = rng.choice([0.1, 0.05, 0.3] if seed % 2 else [0.05]) * direction
            x, y = (x, round(y + step, 3)) if along_y else (round(x + step, 3), y)
            if line == 4 and rng.random() < 0.2:  # a bend too slight to slow down at
                y = round(y + 0.0001, 4)
            if rng.random() < 0.03:
                s_value = rng.choice([400.0, 800.0, 800.0])
            if rng.random() < 0.01:
                feed_mm_s = rng.choice([60.0, 100.0])
            move = Move((x, y), feed_mm_s, MoveKind.FEED, ToolMode.CW, s_value)
            if rng.random() < 0.01:
                move.actions = [Action(ActionName.COOLANT, {"mist": True, "flood": False})]
            job.append(move)
            if rng.random() < 0.005:
                job.append(Action(ActionName.DWELL, {"seconds": 0.01}, lead_s=0.01,
                                  stops_motion=True))
        y = round(y + 0.2, 3)
        job.append(Move((x, y), 100.0, MoveKind.RAPID if line % 2 else MoveKind.FEED,
                        ToolMode.CW, 0.0))
    job.pop()  # it ends on a line's ramp down: motion stops inside a run's tick
    return job


@pytest.mark.parametrize("seed", range(6))
def test_blocks_taken_at_once_are_what_the_loop_makes_of_them_one_by_one(
        monkeypatch: pytest.MonkeyPatch, seed: int) -> None:
    """The step generator takes the blocks that only lengthen the open piece at once
    (``StepGenerator._lengthen``): the board gets the same messages, the backend the same
    pieces (to the last bit), and the step generator publishes the same state after every
    tick, the planner fed as a sender would (and given the job at once), through ticks long
    and short, ticks past the block budget (120 ms of 0.05 mm
    blocks), power changes, feed overrides, actions, dwells, a hold and a halt."""
    rng = random.Random(seed)
    ticks = [rng.choice([0.001, 0.007, 0.02, 0.05, 0.12]) for _ in range(5000)]
    hold_at = rng.randrange(20, 60)
    script: Script = {hold_at: StepGenerator.hold, hold_at + 30: StepGenerator.resume,
                      hold_at + 45: lambda stepgen: stepgen.planner.set_overrides(0.6),
                      hold_at + 55: lambda stepgen: stepgen.planner.set_overrides(1.3)}
    if seed == 5:
        script[hold_at + 50] = StepGenerator.stop_now
    job = random_job(seed)
    power_of = follows_speed if seed % 3 == 0 else None
    states: list[Any] = []
    taken = []
    lengthen = pieces_module.PieceReporter.lengthen

    def counted(self: pieces_module.PieceReporter, *args: Any) -> tuple[int, float]:
        count, left_s = lengthen(self, *args)
        taken.append(count)
        return count, left_s

    monkeypatch.setattr(pieces_module.PieceReporter, "lengthen", counted)
    at_once, pieces = drive(job, True, monkeypatch, dict(script), states, power_of,
                            ticks.__getitem__, fed=seed < 4)
    with monkeypatch.context() as patched:
        patched.setattr(StepGenerator, "_lengthen", one_at_a_time)
        states_one: list[Any] = []
        one_by_one, pieces_one = drive(job, True, patched, dict(script), states_one,
                                       power_of, ticks.__getitem__, fed=seed < 4)
    assert at_once == one_by_one
    assert [repr(p) for p in pieces] == [repr(p) for p in pieces_one]
    assert repr(states) == repr(states_one)
    assert len(states) > 30 and sum(taken) > len(job) / 2, (sum(taken), len(job))
    done = [state[3] for state in states]
    if seed % 2 == 0:  # a 120 ms tick of 0.5 ms blocks: in slices (blocks_per_call)
        assert max(b - a for a, b in zip(done, done[1:], strict=False)) > 128
