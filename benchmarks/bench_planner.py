"""Planner cost: re-planning a full window, and the append/pop pipeline around it.

* re-plan: :meth:`Planner.plan` over 4,096 queued blocks (a raster of short zig-zag segments),
  against the same backward/forward passes and trapezoids written as plain-Python loops
  (:func:`server.motion.trapezoid.plan_window_reference`) on the same window, side by side in this
  process (interleaved rounds, best CPU time of each); and one ``plan()`` call of the live
  planner on that window, which plans ``plan_blocks`` (512) of them with the look-ahead of all;
* pipeline: append + pop per block through a window kept full, re-planning whenever the last
  plan's look-ahead runs short (as the step generator does), in blocks/s.

Run: ``python -m benchmarks planner [--quick] [--json]``, or with a window size and round
count of your own: ``python -m benchmarks.bench_planner [--blocks N] [--rounds R]``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from functools import partial

from benchmarks.common import BenchResult, add_run_options, execute, side_by_side
from server.motion.limits import ACCEL, DURATION, ENTRY, JUNCTION, LEAD, LENGTH, NOMINAL
from server.motion.moves import Move, MoveKind
from server.motion.planner import Planner, PlannerSettings
from server.motion.trapezoid import plan_window_reference

MACHINE = PlannerSettings(
    max_rate_mm_s=(500.0, 500.0, 10.0),
    accel_mm_s2=(3000.0, 3000.0, 200.0),
    max_blocks=4096,
    max_planned_s=1e9,  # bound the window by count only
)
BLOCKS = 4096
ROUNDS, QUICK_ROUNDS = 7, 3
PIPELINE_BLOCKS, QUICK_PIPELINE_BLOCKS = 100_000, 25_000


def raster(count: int) -> list[Move]:
    """Short segments along X with a small Y wiggle, varying feeds (laser-raster-like)."""
    moves = []
    for k in range(1, count + 1):
        feed_mm_s = (50.0, 150.0, 400.0)[k % 3]
        moves.append(Move((0.2 * k, 0.05 * (k % 2), 0.0), feed_mm_s, MoveKind.FEED))
    return moves


def full_window(blocks: int, plan_blocks: int | None = None) -> Planner:
    """A window of ``blocks`` raster blocks, planned ``plan_blocks`` at a time (default: as
    the server does)."""
    machine = MACHINE if plan_blocks is None else replace(MACHINE, plan_blocks=plan_blocks)
    planner = Planner(machine, (0.0, 0.0, 0.0))
    for move in raster(blocks):
        planner.append(move)
    planner.plan()
    return planner


def replan(planner: Planner, times: int) -> None:
    """Force ``times`` full re-plans (alternating the start speed marks the window changed)."""
    for index in range(times):
        planner.set_start_speed(1e-3 * (index & 1))
        planner.plan()


Inputs = tuple[list[float], list[float], list[float], list[float], list[float]]


def reference_inputs(planner: Planner) -> Inputs:
    """Length, acceleration, nominal speed, junction limit and lead time of every block."""
    window = planner._columns.window()  # the benchmark reads the same numbers plan() uses
    rows = (window[row].tolist() for row in (LENGTH, ACCEL, NOMINAL, JUNCTION, LEAD))
    length, accel, nominal, junction, lead = rows
    return length, accel, nominal, junction, lead


def reference_replan(inputs: Inputs, times: int) -> None:
    for index in range(times):
        plan_window_reference(*inputs, start_mm_s=1e-3 * (index & 1))


def check_same_plan(planner: Planner, inputs: Inputs) -> float:
    """Largest difference in block duration (s) between the numpy plan and the loops."""
    planner.set_start_speed(0.0)
    planner.plan()
    ours = planner._columns.window()[DURATION].tolist()
    theirs = plan_window_reference(*inputs, start_mm_s=0.0)[DURATION - ENTRY]
    return max(abs(a - b) for a, b in zip(ours, theirs, strict=True))


def pipeline(machine: PlannerSettings, moves: list[Move]) -> int:
    """Append and pop every move through a full window, re-planning as the step generator does
    (:meth:`StepGenerator.pop_block`: when the head is past the blocks the last plan settled)."""
    planner = Planner(machine, (0.0, 0.0, 0.0))
    popped = 0
    for move in moves:
        planner.append(move)
        if planner.is_full():
            if planner.lookahead_short():
                planner.plan()
            planner.pop()
            popped += 1
    while planner.pop() is not None:
        popped += 1
    return popped


def measure_replan(result: BenchResult, blocks: int, rounds: int) -> None:
    """Re-plans of a full window against the plain-Python loops, side by side, and one call
    of the live planner (a bounded prefix of the same window)."""
    planner, live = full_window(blocks, plan_blocks=blocks), full_window(blocks)
    inputs = reference_inputs(planner)
    ours_times, reference_times = 50, 2
    ours_s, reference_s, live_s = side_by_side(
        rounds,
        lambda: replan(planner, ours_times),
        lambda: reference_replan(inputs, reference_times),
        lambda: replan(live, ours_times),
    )
    ours_us = ours_s / ours_times * 1e6
    reference_us = reference_s / reference_times * 1e6
    live_us = live_s / ours_times * 1e6
    difference_s = check_same_plan(planner, inputs)
    print(f"re-plan of {blocks:,} queued blocks (best of {rounds} interleaved rounds, CPU time)")
    ours_rate = blocks / ours_us * 1e6
    print(f"  numpy prefix scans   {ours_us:10,.0f} µs/re-plan  {ours_rate:14,.0f} blocks/s")
    print(
        f"  plain-Python loops   {reference_us:10,.0f} µs/re-plan  "
        f"{blocks / reference_us * 1e6:14,.0f} blocks/s"
    )
    print(f"  ratio                {reference_us / ours_us:10,.1f}x faster")
    print(f"  same plan: largest duration difference {difference_s:.2e} s")
    prefix = live.settings.plan_blocks
    print(f"  one plan() of the server's planner ({prefix} of the {blocks:,} blocks, the rest "
          f"through one minimum): {live_us:,.0f} µs")
    result.add("replan", "one live plan() call", blocks=(blocks, "blocks"),
               planned=(prefix, "blocks"), replan=(live_us, "µs/call"))
    result.add("replan", "numpy prefix scans", blocks=(blocks, "blocks"),
               replan=(ours_us, "µs/re-plan"), rate=(ours_rate, "blocks/s"))
    result.add("replan", "plain-Python loops", blocks=(blocks, "blocks"),
               replan=(reference_us, "µs/re-plan"), rate=(blocks / reference_us * 1e6, "blocks/s"))
    result.add("replan", "ratio", ratio=(reference_us / ours_us, "x"),
               largest_duration_difference=(difference_s, "s"))


def measure_pipeline(result: BenchResult, moves: list[Move], rounds: int) -> None:
    """Append + pop through a window bounded by count, then by time (the default)."""
    print(f"append + pop of {len(moves):,} blocks through a full window, re-planning as the step "
          "generator does")
    for label, machine in (
        (f"window {MACHINE.max_blocks:,} blocks", MACHINE),
        ("window 0.5 s (default)", replace(MACHINE, max_planned_s=0.5)),
    ):
        run = partial(pipeline, machine, moves)
        (pipeline_s,) = side_by_side(max(1, rounds // 3), run)
        print(
            f"  {label:24} {len(moves) / pipeline_s:12,.0f} blocks/s  "
            f"{pipeline_s / len(moves) * 1e6:6.2f} µs/block"
        )
        result.add("pipeline", label, blocks=(len(moves), "blocks"),
                   rate=(len(moves) / pipeline_s, "blocks/s"),
                   per_block=(pipeline_s / len(moves) * 1e6, "µs/block"))


def run(quick: bool, blocks: int = BLOCKS, rounds: int | None = None) -> BenchResult:
    """Quick: 3 rounds instead of 7, and 25,000 blocks through the pipeline instead of 100,000."""
    result = BenchResult("planner", quick)
    rounds = rounds or (QUICK_ROUNDS if quick else ROUNDS)
    measure_replan(result, blocks, rounds)
    measure_pipeline(result, raster(QUICK_PIPELINE_BLOCKS if quick else PIPELINE_BLOCKS), rounds)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=BLOCKS)
    parser.add_argument("--rounds", type=int, default=None)
    add_run_options(parser)
    options = parser.parse_args(argv)
    measure = partial(run, options.quick, options.blocks, options.rounds)
    return execute([measure], options.json)


if __name__ == "__main__":
    sys.exit(main())
