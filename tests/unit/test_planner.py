"""The look-ahead planner: trapezoids, junction speeds, the window, actions and overrides."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.machine.parts import planner_settings
from server.motion.block import Block
from server.motion.moves import Action, Move, MoveKind
from server.motion.planner import MIN_LENGTH_MM, Planner, PlannerSettings
from server.motion.planner_intake import RUN_SLICE
from server.motion.trapezoid import junction_speed_sq, plan_window, plan_window_reference

XYZ = PlannerSettings(max_rate_mm_s=(500.0, 500.0, 50.0), accel_mm_s2=(1000.0, 1000.0, 100.0))


def feed_to(*target: float, feed_mm_s: float = 100.0, kind: MoveKind = MoveKind.FEED) -> Move:
    return Move(tuple(float(x) for x in target), feed_mm_s, kind)


def run(planner: Planner) -> list[Block]:
    """Plan and pop everything waiting."""
    planner.plan()
    return list(iter(planner.pop, None))


def plan_path(points: list[tuple[float, ...]], feed_mm_s: float = 100.0) -> list[Block]:
    planner = Planner(XYZ, points[0])
    for point in points[1:]:
        planner.append(feed_to(*point, feed_mm_s=feed_mm_s))
    return run(planner)


def ramp_distance_mm(block: Block) -> float:
    """Distance the three phases cover, computed from the profile alone."""
    entry, cruise, exit_ = block.entry_mm_s, block.cruise_mm_s, block.exit_mm_s
    return (
        0.5 * (entry + cruise) * block.accel_s
        + cruise * block.cruise_s
        + 0.5 * (cruise + exit_) * block.decel_s
    )


def assert_kinematics(blocks: list[Block], start_mm_s: float = 0.0) -> None:
    """Acceleration within limits everywhere, speed continuous, every block covers its length."""
    speed = start_mm_s
    for block in blocks:
        assert abs(block.speed_at(0.0) - speed) <= 1e-9
        assert block.duration_s == pytest.approx(block.motion_s + block.lead_s, abs=1e-12)
        assert ramp_distance_mm(block) == pytest.approx(block.length_mm, rel=1e-9, abs=1e-12)
        assert block.distance_at(block.duration_s) == block.length_mm
        if block.motion_s > 0.0:
            times = np.linspace(0.0, block.motion_s, 64)
            speeds = np.array([block.speed_at(t) for t in times])
            step_s = times[1] - times[0]
            limit = block.accel_mm_s2 * step_s * (1 + 1e-9) + 1e-12
            assert np.all(np.abs(np.diff(speeds)) <= limit)
            assert np.all(speeds >= 0.0)
            distances = np.array([block.distance_at(t) for t in times])
            assert np.all(np.diff(distances) >= 0.0)
        speed = block.speed_at(block.duration_s)
        assert abs(speed - block.exit_mm_s) <= 1e-9
    assert speed <= 1e-9, "motion stops at the end of the queue"


# ---------------------------------------------------------------- trapezoids


def test_a_single_long_move_reaches_cruise_with_the_exact_trapezoid_times() -> None:
    (block,) = plan_path([(0.0, 0.0, 0.0), (100.0, 0.0, 0.0)], feed_mm_s=50.0)
    assert (block.entry_mm_s, block.cruise_mm_s, block.exit_mm_s) == (0.0, 50.0, 0.0)
    assert block.accel_s == pytest.approx(0.05, abs=1e-12)  # 50 mm/s / 1000 mm/s²
    assert block.decel_s == pytest.approx(0.05, abs=1e-12)
    assert block.cruise_s == pytest.approx((100.0 - 2 * 1.25) / 50.0, abs=1e-12)
    assert block.duration_s == pytest.approx(2.05, abs=1e-12)
    assert block.distance_at(0.05) == pytest.approx(1.25, abs=1e-12)
    assert block.distance_at(1.0) == pytest.approx(1.25 + 50.0 * 0.95, abs=1e-12)
    assert block.speed_at(0.025) == pytest.approx(25.0, abs=1e-12)
    assert block.position_at(block.duration_s) == (100.0, 0.0, 0.0)


def test_short_moves_give_triangular_profiles() -> None:
    (block,) = plan_path([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)], feed_mm_s=100.0)
    peak_mm_s = math.sqrt(1000.0 * 1.0)  # accelerate over half, decelerate over half
    assert block.cruise_mm_s == pytest.approx(peak_mm_s, rel=1e-12)
    assert block.cruise_s == pytest.approx(0.0, abs=1e-12)
    assert block.accel_s == pytest.approx(peak_mm_s / 1000.0, rel=1e-12)
    assert block.decel_s == pytest.approx(block.accel_s, rel=1e-12)
    assert block.distance_at(block.accel_s) == pytest.approx(0.5, rel=1e-9)


def test_nominal_speed_is_limited_by_the_axes_max_rates_projected_on_the_direction() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 10.0, feed_mm_s=1000.0))  # 45° in XZ; Z allows 50 mm/s
    (block,) = run(planner)
    assert block.nominal_mm_s == pytest.approx(50.0 * math.sqrt(2.0), rel=1e-12)
    assert block.accel_mm_s2 == pytest.approx(100.0 * math.sqrt(2.0), rel=1e-12)


def test_nominal_speed_never_drops_below_min_feed() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(1.0, 0.0, 0.0, feed_mm_s=0.0))
    (block,) = run(planner)
    assert block.nominal_mm_s == XYZ.min_feed_mm_s


def test_rapids_run_at_the_axes_max_rate() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(300.0, 0.0, 0.0, feed_mm_s=1.0, kind=MoveKind.RAPID))
    (block,) = run(planner)
    assert block.cruise_mm_s == 500.0


# ---------------------------------------------------------------- junctions


def test_a_90_degree_corner_slows_to_the_junction_speed_the_formula_gives() -> None:
    first, second = plan_path([(0.0, 0.0, 0.0), (50.0, 0.0, 0.0), (50.0, 50.0, 0.0)], 150.0)
    sin_half = math.sin(math.pi / 4)  # θ = 90° between the reversed first and the second
    expected = math.sqrt(1000.0 * 0.01 * sin_half / (1 - sin_half))
    assert first.exit_mm_s == pytest.approx(expected, rel=1e-12)
    assert second.entry_mm_s == first.exit_mm_s
    assert first.cruise_mm_s == 150.0


def test_a_reversal_stops_and_straight_on_is_unlimited() -> None:
    assert junction_speed_sq((1.0, 0.0), (-1.0, 0.0), 1000.0, 0.01) == 0.0
    assert junction_speed_sq((1.0, 0.0), (1.0, 0.0), 1000.0, 0.01) == math.inf
    first, _ = plan_path([(0.0, 0.0, 0.0), (50.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
    assert first.exit_mm_s == 0.0


def test_a_junction_is_capped_by_the_slower_blocks_nominal_speed() -> None:
    first, second = plan_path([(0.0, 0.0, 0.0), (50.0, 0.0, 0.0), (100.0, 0.0, 0.0)])
    assert first.exit_mm_s == pytest.approx(100.0)
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(50.0, 0.0, 0.0, feed_mm_s=200.0))
    planner.append(feed_to(100.0, 0.0, 0.0, feed_mm_s=20.0))
    first, second = run(planner)
    assert first.exit_mm_s == pytest.approx(20.0)
    assert second.cruise_mm_s == pytest.approx(20.0)


def test_a_straight_line_split_into_1000_pieces_plans_the_same_total_time_as_one_piece() -> None:
    (whole,) = plan_path([(0.0, 0.0, 0.0), (100.0, 0.0, 0.0)], feed_mm_s=50.0)
    pieces = plan_path([(0.1 * k, 0.0, 0.0) for k in range(1001)], feed_mm_s=50.0)
    assert len(pieces) == 1000
    assert sum(block.duration_s for block in pieces) == pytest.approx(whole.duration_s, abs=1e-6)
    assert_kinematics(pieces)


def test_a_diagonal_line_split_into_pieces_does_not_slow_at_the_joins() -> None:
    pieces = plan_path([(0.3 * k, 0.7 * k, 0.01 * k) for k in range(200)], feed_mm_s=50.0)
    cruising = [block for block in pieces if block.entry_mm_s > 49.999]
    assert len(cruising) > 150


# ---------------------------------------------------------------- acceleration limits


def test_acceleration_is_never_exceeded_on_a_zigzag_with_mixed_feeds() -> None:
    rng = random.Random(7)
    points = [(rng.uniform(0, 5), rng.uniform(0, 5), rng.uniform(0, 0.5)) for _ in range(300)]
    planner = Planner(XYZ, points[0])
    for point in points[1:]:
        planner.append(feed_to(*point, feed_mm_s=rng.choice([5.0, 50.0, 400.0])))
    assert_kinematics(run(planner))


coordinate = st.floats(-50.0, 50.0, allow_nan=False)
point_2d = st.tuples(coordinate, coordinate)
axis_limits = st.tuples(st.floats(10.0, 1000.0), st.floats(10.0, 1000.0))


@st.composite
def machine_and_path(draw: st.DrawFn) -> tuple[PlannerSettings, list[Move], list[int]]:
    rates, accels = draw(axis_limits), draw(axis_limits)
    deviation = draw(st.floats(0.001, 1.0))
    machine = PlannerSettings(rates, accels, junction_deviation_mm=deviation)
    points = draw(st.lists(point_2d, min_size=1, max_size=40))
    kinds = st.sampled_from([MoveKind.FEED, MoveKind.FEED, MoveKind.RAPID])
    moves = [Move(p, draw(st.floats(0.5, 2000.0)), draw(kinds)) for p in points]
    dwells = draw(st.lists(st.integers(0, len(moves)), max_size=3))
    return machine, moves, dwells


def append_all(planner: Planner, moves: list[Move], dwells: list[int], start: int = 0) -> None:
    for index, move in enumerate(moves, start):
        if index in dwells:
            planner.append_action(Action("dwell", lead_s=0.25))
        planner.append(move)


@settings(max_examples=150, deadline=None)
@given(machine_and_path())
def test_acceleration_is_never_exceeded_on_random_polylines(
    case: tuple[PlannerSettings, list[Move], list[int]],
) -> None:
    machine, moves, dwells = case
    planner = Planner(machine, (0.0, 0.0))
    append_all(planner, moves, dwells)
    blocks = run(planner)
    assert_kinematics(blocks)
    for block in blocks:
        assert block.cruise_mm_s <= block.nominal_mm_s * (1 + 1e-12) or block.move is None
    for before, after in zip(blocks, blocks[1:], strict=False):
        if before.move is None or after.move is None:
            assert after.entry_mm_s == 0.0
            continue
        limit_sq = junction_speed_sq(
            before.unit,
            after.unit,
            min(before.accel_mm_s2, after.accel_mm_s2),
            machine.junction_deviation_mm,
        )
        assert after.entry_mm_s <= math.sqrt(limit_sq) * (1 + 1e-9) + 1e-9


@settings(max_examples=100, deadline=None)
@given(machine_and_path(), st.lists(st.integers(1, 6), min_size=1), st.data())
def test_popping_between_batches_of_appends_stays_within_the_acceleration_limit(
    case: tuple[PlannerSettings, list[Move], list[int]], batches: list[int], data: st.DataObject
) -> None:
    machine, moves, dwells = case
    planner = Planner(machine, (0.0, 0.0))
    popped: list[Block] = []
    done = 0
    for size in batches * len(moves):
        append_all(planner, moves[done : done + size], dwells, done)
        done += size
        if data.draw(st.booleans()):
            planner.plan()
        for _ in range(data.draw(st.integers(0, 3))):
            block = planner.pop()
            popped += [block] if block else []
        if done >= len(moves):
            break
    popped += run(planner)
    assert_kinematics(popped)


@settings(max_examples=100, deadline=None)
@given(machine_and_path(), st.lists(st.integers(1, 8), min_size=1))
def test_incremental_batch_planning_equals_planning_the_whole_path_at_once(
    case: tuple[PlannerSettings, list[Move], list[int]], batches: list[int]
) -> None:
    machine, moves, dwells = case
    whole = Planner(machine, (0.0, 0.0))
    append_all(whole, moves, dwells)
    batched = Planner(machine, (0.0, 0.0))
    done = 0
    while done < len(moves):
        size = batches[done % len(batches)]
        append_all(batched, moves[done : done + size], dwells, done)
        batched.plan()
        done += size
    if len(moves) in dwells:
        batched.append_action(Action("dwell", lead_s=0.25))
        whole.append_action(Action("dwell", lead_s=0.25))
    assert run(batched) == run(whole)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0.0, 20.0), st.floats(1.0, 5000.0), st.floats(0.01, 500.0)),
        min_size=1,
        max_size=60,
    ),
    st.floats(0.0, 50.0),
    st.randoms(use_true_random=False),
)
def test_the_numpy_prefix_scans_equal_the_plain_python_passes(
    blocks: list[tuple[float, float, float]], start_mm_s: float, rng: random.Random
) -> None:
    length, accel, nominal = (list(column) for column in zip(*blocks, strict=True))
    junction = [rng.choice([0.0, 1.0, 100.0, math.inf]) for _ in blocks]
    lead = [0.0] * len(blocks)
    out = np.empty((7, len(blocks)))
    arrays = (np.array(column) for column in (length, accel, nominal, junction, lead))
    length_a, accel_a, nominal_a, junction_a, lead_a = arrays
    plan_window(length_a, accel_a, nominal_a, junction_a, lead_a, start_mm_s, out)
    expected = plan_window_reference(length, accel, nominal, junction, lead, start_mm_s)
    scale_sq = 2 * sum(a * d for a, d in zip(accel, length, strict=True)) + start_mm_s**2 + 1.0
    speeds_sq, expected_sq = out[:3] ** 2, np.array(expected[:3]) ** 2  # v² is what is summed
    np.testing.assert_allclose(speeds_sq, expected_sq, rtol=1e-9, atol=1e-12 * scale_sq)
    assert out[6].sum() == pytest.approx(sum(expected[6]), rel=1e-9, abs=1e-6)


# ---------------------------------------------------------------- the window


def test_the_window_is_full_by_block_count() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_blocks=8, max_planned_s=60.0)
    planner = Planner(machine, (0.0,))
    for k in range(1, 8):
        planner.append(feed_to(float(k)))
        assert not planner.is_full()
    planner.append(feed_to(8.0))
    assert planner.is_full()
    assert len(planner) == 8
    planner.pop()
    assert not planner.is_full()


def test_the_window_is_full_by_planned_time() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_planned_s=0.5)
    planner = Planner(machine, (0.0,))
    for k in range(1, 5):  # 10 mm at 100 mm/s: 0.1 s each at the nominal speed
        planner.append(feed_to(10.0 * k))
    assert planner.planned_time_s() == pytest.approx(0.4)
    assert not planner.is_full()
    planner.plan()  # ramps make the planned time longer than the nominal estimate
    assert planner.planned_time_s() == pytest.approx(0.4 + 0.1, abs=1e-12)
    assert planner.is_full()
    first = planner.pop()
    assert first is not None
    assert planner.planned_time_s() == pytest.approx(0.5 - first.duration_s, abs=1e-12)


def test_a_full_window_has_room_again_once_a_sixteenth_of_its_blocks_has_drained() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_blocks=64, max_planned_s=60.0)
    planner = Planner(machine, (0.0,))
    for k in range(1, 65):
        planner.append(feed_to(float(k)))
    assert planner.is_full() and not planner.has_room()
    planner.plan()
    for left in range(63, 59, -1):  # 63, 62, 61: neither full nor room for a batch
        planner.pop()
        assert not planner.is_full()
        assert planner.has_room() is (left <= 60), left


def test_a_full_window_has_room_again_once_a_sixteenth_of_its_time_has_drained() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_planned_s=1.6)
    planner = Planner(machine, (0.0,))
    for k in range(1, 17):  # 10 mm at 100 mm/s: 0.1 s each at the nominal speed
        planner.append(feed_to(10.0 * k))
    planner.plan()
    assert planner.is_full() and not planner.has_room()
    while planner.planned_time_s() > 1.5 + 1e-9:
        assert not planner.has_room()
        planner.pop()
    assert planner.has_room()


def test_a_window_of_two_blocks_has_room_after_one_pop_and_is_never_both() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_blocks=2, max_planned_s=60.0)
    planner = Planner(machine, (0.0,))
    assert planner.has_room()
    planner.append(feed_to(1.0))
    assert planner.has_room()
    planner.append(feed_to(2.0))
    assert planner.is_full() and not planner.has_room()
    planner.plan()
    planner.pop()
    assert planner.has_room() and not planner.is_full()


def test_the_window_is_never_full_with_fewer_than_two_blocks() -> None:
    machine = PlannerSettings((500.0,), (1000.0,), max_planned_s=0.5)
    planner = Planner(machine, (0.0,))
    planner.append(feed_to(1000.0, feed_mm_s=1.0))
    planner.plan()
    assert planner.planned_time_s() > 999.0
    assert not planner.is_full()
    planner.append(feed_to(1001.0, feed_mm_s=1.0))
    assert planner.is_full()


def test_the_window_grows_past_its_first_capacity_and_back() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    popped: list[Block] = []
    for k in range(1, 3000):
        planner.append(feed_to(0.1 * k, 0.05 * (k % 2), 0.0))
        if k % 97 == 0:
            planner.plan()
            popped += [planner.pop() for _ in range(40)]  # type: ignore[misc]
    popped += run(planner)
    assert len(popped) == 2999
    assert popped[-1].end_mm == (0.1 * 2999, 0.05, 0.0)
    assert all(b.end_mm == a.start_mm for b, a in zip(popped, popped[1:], strict=False))
    assert_kinematics(popped)


def test_pop_uses_the_last_plan_for_the_head_after_more_appends() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append(feed_to(20.0, 0.0, 0.0))
    planner.plan()
    planner.append(feed_to(30.0, 0.0, 0.0))
    first = planner.pop()
    assert first is not None and first.exit_mm_s == pytest.approx(100.0)
    second = planner.pop()
    assert second is not None and second.exit_mm_s == 0.0  # planned before the third arrived
    third = planner.pop()
    assert third is not None and third.entry_mm_s == 0.0
    assert_kinematics([first, second, third])


def test_set_start_speed_is_the_entry_of_the_next_popped_block() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(100.0, 0.0, 0.0))
    planner.plan()
    planner.set_start_speed(60.0)
    block = planner.pop()
    assert block is not None
    assert block.entry_mm_s == 60.0
    assert block.cruise_mm_s == 100.0
    assert_kinematics([block], start_mm_s=60.0)


# ---------------------------------------------------------------- actions


def spindle(s: float) -> Action:
    return Action("spindle", {"s": s})


def test_follow_actions_ride_on_the_next_block_without_stopping_motion() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append_action(spindle(500.0))
    planner.append_action(Action("coolant", {"mist": True}))
    planner.append(feed_to(20.0, 0.0, 0.0))
    first, second = run(planner)
    assert first.actions == []
    assert [action.name for action in second.actions] == ["spindle", "coolant"]
    assert first.exit_mm_s == pytest.approx(100.0)
    assert second.entry_mm_s == first.exit_mm_s


def test_a_dwell_forces_a_stop() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append_action(spindle(200.0))
    planner.append_action(Action("dwell", lead_s=0.5))
    planner.append(feed_to(20.0, 0.0, 0.0))
    before, dwell, after = run(planner)
    assert before.exit_mm_s == 0.0
    assert dwell.move is None and dwell.length_mm == 0.0
    assert [action.name for action in dwell.actions] == ["spindle", "dwell"]
    assert (dwell.entry_mm_s, dwell.exit_mm_s, dwell.duration_s) == (0.0, 0.0, 0.5)
    assert dwell.start_mm == dwell.end_mm == (10.0, 0.0, 0.0)
    assert after.entry_mm_s == 0.0


def test_a_pause_stops_motion_and_takes_no_time() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append_action(Action("pause", stops_motion=True))
    planner.append(feed_to(20.0, 0.0, 0.0))
    before, pause, after = run(planner)
    assert before.exit_mm_s == after.entry_mm_s == 0.0
    assert pause.duration_s == 0.0


def test_pending_follow_actions_pop_as_an_action_only_block_when_no_motion_waits() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append_action(spindle(0.0))
    assert len(planner) == 2
    planner.pop()
    assert len(planner) == 1
    block = planner.pop()
    assert block is not None and block.move is None
    assert [action.name for action in block.actions] == ["spindle"]
    assert (block.duration_s, block.start_mm) == (0.0, (10.0, 0.0, 0.0))
    assert planner.pop() is None and len(planner) == 0


def test_zero_length_moves_are_dropped_and_their_actions_carry_over() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(Move((0.0, 0.0, 0.0), 100.0, MoveKind.FEED, actions=[spindle(100.0)]))
    planner.append(feed_to(0.1 * MIN_LENGTH_MM, 0.0, 0.0))
    assert len(planner) == 1  # only the pending action
    planner.append(feed_to(10.0, 0.0, 0.0))
    (block,) = run(planner)
    assert [action.name for action in block.actions] == ["spindle"]
    assert block.start_mm == (0.0, 0.0, 0.0)
    assert planner.position_mm == (10.0, 0.0, 0.0)


# ---------------------------------------------------------------- overrides, halt, hold


def test_overrides_scale_the_nominal_speeds_of_waiting_blocks() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(100.0, 0.0, 0.0, feed_mm_s=100.0))
    planner.append(feed_to(100.0, 100.0, 0.0, kind=MoveKind.RAPID))
    planner.append(feed_to(0.0, 100.0, 0.0, feed_mm_s=100.0, kind=MoveKind.JOG))
    planner.plan()
    planner.set_overrides(feed=0.5, rapid=0.25)
    feed, rapid, jog = run(planner)
    assert feed.nominal_mm_s == feed.cruise_mm_s == 50.0
    assert rapid.nominal_mm_s == 125.0
    assert jog.nominal_mm_s == 100.0


def test_feed_override_stays_under_the_axis_max_rate_and_is_clamped() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.set_overrides(feed=5.0, rapid=0.0)
    planner.append(feed_to(100.0, 0.0, 0.0, feed_mm_s=400.0))
    planner.append(feed_to(100.0, 100.0, 0.0, kind=MoveKind.RAPID))
    fast, rapid = run(planner)
    assert fast.nominal_mm_s == 500.0  # 400 × 2.0 capped by X's 500 mm/s
    assert rapid.nominal_mm_s == 125.0  # rapid override clamped to 25 %


def test_lowering_the_feed_override_under_a_moving_block_decelerates_within_the_limit() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    for k in range(1, 40):
        planner.append(feed_to(10.0 * k, 0.0, 0.0, feed_mm_s=400.0))
    planner.plan()
    popped = [planner.pop() for _ in range(15)]
    assert popped[-1] is not None and popped[-1].exit_mm_s == pytest.approx(400.0)
    planner.set_overrides(feed=0.1)
    rest = run(planner)
    assert rest[0].entry_mm_s == popped[-1].exit_mm_s
    assert rest[-1].cruise_mm_s == pytest.approx(40.0)
    assert_kinematics([*popped, *rest])  # type: ignore[list-item]


def test_flush_returns_the_dropped_actions_in_order() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append_action(spindle(1.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    planner.append_action(Action("dwell", lead_s=1.0))
    planner.append(feed_to(20.0, 0.0, 0.0))
    planner.append_action(spindle(0.0))
    dropped = planner.flush()
    assert [(a.name, a.params.get("s")) for a in dropped] == [
        ("spindle", 1.0),
        ("dwell", None),
        ("spindle", 0.0),
    ]
    assert len(planner) == 0 and planner.pop() is None and planner.planned_time_s() == 0.0
    planner.set_position((3.0, 4.0, 0.0))
    planner.append(feed_to(3.0, 14.0, 0.0))
    (block,) = run(planner)
    assert (block.start_mm, block.entry_mm_s) == ((3.0, 4.0, 0.0), 0.0)


def test_set_position_refuses_while_blocks_are_waiting() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(10.0, 0.0, 0.0))
    with pytest.raises(RuntimeError):
        planner.set_position((0.0, 0.0, 0.0))


def test_insert_front_gives_a_remainder_that_starts_from_zero() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(100.0, 0.0, 0.0))
    planner.append(feed_to(200.0, 0.0, 0.0))
    planner.plan()
    executing = planner.pop()
    assert executing is not None and executing.exit_mm_s == pytest.approx(100.0)
    held_at = executing.position_at(0.5)  # feed hold: the step generator stopped here
    remainder = planner.make_block(held_at, executing.end_mm, executing.move, [])
    assert remainder.length_mm == pytest.approx(100.0 - executing.distance_at(0.5))
    planner.insert_front(remainder)
    assert len(planner) == 2
    resumed, following = run(planner)
    assert resumed.start_mm == held_at and resumed.end_mm == (100.0, 0.0, 0.0)
    assert resumed.entry_mm_s == 0.0
    assert resumed.exit_mm_s == following.entry_mm_s == pytest.approx(100.0)
    assert_kinematics([resumed, following])


def test_settings_come_from_the_machine_config() -> None:
    from server.config import CoreConfig

    core = CoreConfig.model_validate(
        {
            "axes": {
                "x": {"steps_per_mm": 80, "max_rate_mm_s": 300, "accel_mm_s2": 2000, "max_mm": 400},
                "y": {"steps_per_mm": 80, "max_rate_mm_s": 200, "accel_mm_s2": 1500, "max_mm": 300},
            },
            "planner": {"junction_deviation_mm": 0.02, "max_blocks": 64, "max_planned_s": 2.0},
        }
    )
    machine = planner_settings(core)
    assert machine.max_rate_mm_s == (300.0, 200.0)
    assert machine.accel_mm_s2 == (2000.0, 1500.0)
    assert (machine.junction_deviation_mm, machine.max_blocks, machine.max_planned_s) == (
        0.02,
        64,
        2.0,
    )


def test_new_settings_apply_to_blocks_appended_afterwards() -> None:
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    planner.append(feed_to(100.0, 0.0, 0.0, feed_mm_s=1000.0))
    planner.settings = PlannerSettings((200.0, 200.0, 50.0), (1000.0, 1000.0, 100.0))
    planner.append(feed_to(100.0, 100.0, 0.0, feed_mm_s=1000.0))
    before, after = run(planner)
    assert (before.nominal_mm_s, after.nominal_mm_s) == (500.0, 200.0)


def test_insert_front_derives_the_limits_of_blocks_appended_but_not_yet_planned() -> None:
    planner = Planner(PlannerSettings((100.0, 40.0, 10.0), (1000.0, 400.0, 100.0)),
                      (0.0, 0.0, 0.0))
    planner.append(Move((10.0, 0.0, 0.0), 50.0, MoveKind.FEED))
    head = planner.pop()
    assert head is not None
    planner.append(Move((10.0, 20.0, 0.0), 50.0, MoveKind.FEED))  # staged, limits not derived
    planner.insert_front(planner.make_block((5.0, 0.0, 0.0), (10.0, 0.0, 0.0), head.move, []))
    with np.errstate(all="raise"):
        rest, turn = planner.pop(), planner.pop()
    assert rest is not None and turn is not None
    assert (rest.length_mm, rest.accel_mm_s2) == (5.0, 1000.0)
    assert (turn.length_mm, turn.accel_mm_s2, turn.nominal_mm_s) == (20.0, 400.0, 40.0)


def test_a_plan_made_before_more_appends_does_not_settle_the_head_exit() -> None:
    """plan(), then appends, then pop: the head was planned to stop at the old window end, so
    the look-ahead is short and a re-plan lets it carry its speed into the new block."""
    planner = Planner(PlannerSettings((500.0, 500.0), (3000.0, 3000.0)), (0.0, 0.0))
    planner.append(Move((10.0, 0.0), 100.0, MoveKind.FEED))
    planner.plan()
    planner.append(Move((20.0, 0.0), 100.0, MoveKind.FEED))
    assert planner.lookahead_short()
    planner.plan()
    head = planner.pop()
    assert head is not None and head.exit_mm_s == pytest.approx(100.0)


@pytest.mark.parametrize(("seed", "window"), [(0, 40), (1, 40), (2, 40), (3, 1400)])
def test_a_run_appended_at_once_plans_the_blocks_of_its_moves_one_by_one(
        seed: int, window: int) -> None:
    """:meth:`Planner.append_run` (a job's plain lines, planned) against :meth:`append`: the
    same blocks, rows and geometry to the bit, through full windows (of 40 blocks; of 1,400,
    taken in several slices of RUN_SLICE at once), rapids, feeds of 0, a move shorter than
    MIN_LENGTH_MM and actions pending before the run."""
    rng = random.Random(seed)
    settings = PlannerSettings(max_rate_mm_s=(500.0, 500.0, 50.0),
                               accel_mm_s2=(1000.0, 1000.0, 100.0), max_blocks=window,
                               max_planned_s=0.5 if window < RUN_SLICE else 1e9,
                               sync_blocks=16)
    here, moves = (0.0, 0.0, 0.0), []
    for index in range(1500):
        step = MIN_LENGTH_MM / 2 if index == 700 else rng.choice([0.1, 0.37, 2.0, 25.0])
        here = (here[0] + step * rng.choice([1, -1]), here[1] + rng.choice([0.0, step]),
                here[2] + (step if index % 97 == 0 else 0.0))
        moves.append(Move(here, rng.choice([0.0, 20.0, 100.0, 400.0]),
                          MoveKind.RAPID if rng.random() < 0.1 else MoveKind.FEED))
    ends = np.asarray([move.target_mm for move in moves])
    feeds = np.asarray([move.feed_mm_s for move in moves])
    rapid = np.asarray([move.kind is MoveKind.RAPID for move in moves])
    taken_by, most = {}, 0
    for at_once in (False, True):
        planner = Planner(settings, (0.0, 0.0, 0.0))
        planner.append_action(Action("switch", {"on": True}))
        popped, index = [], 0
        while index < len(moves):
            if at_once:
                taken = planner.append_run(moves[index:], ends[index:], feeds[index:],
                                           rapid[index:])
                index, most = index + taken, max(most, taken)
            else:
                while index < len(moves) and not planner.append(moves[index]):
                    index += 1
                index += 1 if index < len(moves) else 0
            settled = planner.pop_settled()
            popped.append((settled.rows.tobytes(), settled.geometry) if settled else None)
        popped += [(block.entry_mm_s, block.exit_mm_s, block.move) for block in run(planner)]
        taken_by[at_once] = (popped, planner.moves_appended, planner.position_mm)
    assert len(taken_by[True][0]) > 1500 / window
    assert most > RUN_SLICE if window > RUN_SLICE else most <= window, most
    assert taken_by[True] == taken_by[False]


def test_blocks_popped_past_the_geometry_compactions_keep_their_own_geometry() -> None:
    """Popped blocks' geometry is dropped from the list in batches (GEOMETRY_COMPACT): across
    several batches, each block still carries its own move, start and end, in order."""
    planner = Planner(XYZ, (0.0, 0.0, 0.0))
    targets, popped = [], []
    for i in range(1, 3500):
        target = (float(i % 2), float(i), 0.0)
        targets.append(target)
        planner.append(Move(target, 50.0, MoveKind.FEED))
        if i > 40:  # a window of about forty blocks: compactions come every 1,024 pops
            block = planner.pop()
            assert block is not None and block.move is not None
            popped.append((block.move.target_mm, block.end_mm))
    while (block := planner.pop()) is not None:
        assert block.move is not None
        popped.append((block.move.target_mm, block.end_mm))
    assert [move for move, _ in popped] == [end for _, end in popped] == targets
