"""A redefined position (homing, G92 in machine terms) moves the Klipper backend's step count
without a step: the real planner, step generator and backend on a virtual clock, every message
decoded (the check runs where a block starts, not on every piece)."""

from __future__ import annotations

from typing import Any

import pytest

from benchmarks.bench_klipper_host import Listener, OfflineBackend
from server.backends.klipper import schedule
from server.config_loader import build_config
from server.machine.parts import planner_settings
from server.motion.moves import Move, MoveKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from tests.unit.test_klipper_mcu_time import CLOCK_HZ, FittedMcu


def run_until_idle(stepgen: StepGenerator, backend: OfflineBackend, mcu: FittedMcu,
                   now_s: float) -> float:
    stepgen.request_start()
    for _ in range(5000):  # to the end of the motion and a lead past it
        now_s += 0.001
        backend.now_s = mcu.link.now_s = now_s
        stepgen.tick(now_s)
        if stepgen.idle and not backend.ticks_when_idle:
            break
    return now_s


def x_steps(messages: list[tuple[str, Any]]) -> list[int]:
    """The X axis' (oid 0) steps, signed by the direction last set before them."""
    direction, out = 1, []
    for name, p in messages:
        if name == "set_next_step_dir" and p["oid"] == 0:
            direction = 1 if p["dir"] else -1
        elif name == "queue_step" and p["oid"] == 0:
            out.append(direction * p["count"])
    return out


def test_a_redefined_position_between_blocks_sends_no_step_and_moves_on_from_there(
        monkeypatch: pytest.MonkeyPatch) -> None:
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 300, "accel_mm_s2": 3000, "max_mm": 400}
            for a in "xy"}
    pins = {"x": {"step_pin": "PB13", "dir_pin": "PB12"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2"}}
    core = build_config({"axes": axes, "backend": {
        "kind": "klipper", "serial": "/dev/null", "axes": pins}}).core
    backend, mcu = OfflineBackend(core), FittedMcu(CLOCK_HZ)
    backend.mcu, backend.ready = mcu, True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.configure(oid, mcu.dictionary, backend.cfg.max_error_s * CLOCK_HZ)
    looked, pieces, moved = [], [], []  # the starts checked, all pieces, those rebased
    check, rebased, trajectory = schedule.off_track, backend._rebased, backend.trajectory
    monkeypatch.setattr(schedule, "off_track",
                        lambda steps, start: (looked.append(start), check(steps, start))[1])
    backend._rebased = lambda piece: (moved.append(piece), rebased(piece))[1]  # type: ignore[method-assign]
    backend.trajectory = lambda piece: (pieces.append(piece), trajectory(piece))[1]  # type: ignore[method-assign]
    planner = Planner(planner_settings(core), (0.0, 0.0))
    stepgen = StepGenerator(planner, backend, (80.0, 80.0), Listener())
    stepgen.tick(0.0)
    for end in ((10.0, 0.0), (20.0, 0.0)):  # two blocks, several pieces each
        planner.append(Move(end, 100.0, MoveKind.FEED, ToolMode.OFF, 0.0))
    now_s = run_until_idle(stepgen, backend, mcu, 0.0)
    assert sum(x_steps(mcu.link.messages)) == 1600 and backend.axes[0].position == 1600
    # as the machine redefines its position (homing; G92 in machine terms): idle, no motion
    stepgen.rebase((0.0, 0.0))
    planner.set_position((0.0, 0.0))
    planner.append(Move((5.0, 0.0), 100.0, MoveKind.FEED, ToolMode.OFF, 0.0))
    run_until_idle(stepgen, backend, mcu, now_s)
    steps = x_steps(mcu.link.messages)
    assert all(count > 0 for count in steps), "no step back to the old zero"
    assert sum(steps) == 1600 + 400 and backend.axes[0].position == 400
    moving = [p for p in pieces if p.duration_s > 0.0]
    assert len(moving) > 3 and len(looked) == len({id(p.unit) for p in moving}) == 3
    assert [p.start_mm for p in moved] == [(0.0, 0.0)]  # only the block that starts elsewhere
