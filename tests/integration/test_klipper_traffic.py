"""What a long move costs on the wire to a virtual Klipper MCU (its bytes decoded with Klipper's
own msgproto): cruise runs as long as the hold-back allows (the first, the hold-back less the
share a sample sends ahead of its turn), each still leaving the stall ride-through ahead of its
first step, and the clock polls riding in the steps' blocks."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import pytest

from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.schedule import SHARE_OF_HOLD_BACK
from tests.integration.test_klipper_backend import check_steps, run_job
from tests.support.klipper_machine import klipper_config, klipper_machine
from tests.support.virtual_mcu import VirtualMcu

SPEED_MM_S = 100.0
STEPS_PER_MM = 80.0  # tests/conftest.py's X
ACCEL_MM_S2 = 3000.0


@pytest.fixture
def mcu() -> Iterator[VirtualMcu]:
    virtual = VirtualMcu(id_offset=11, drift_ppm=40.0).start()
    yield virtual
    virtual.stop()


def test_the_hold_back_is_the_lead_but_the_ride_through_and_a_quarter_of_a_short_lead() -> None:
    def hold_back_s(lead_s: float) -> float:
        return KlipperBackend(klipper_config("/dev/null", lead_s).core).hold_back_s

    assert hold_back_s(0.3) == pytest.approx(0.15)  # the default: 130 ms ride-through
    assert hold_back_s(0.5) == pytest.approx(0.35)
    assert hold_back_s(0.2) == pytest.approx(0.05)  # a quarter, 130 ms ride-through still
    assert hold_back_s(0.1) == pytest.approx(0.025)  # a quarter: 55 ms ride-through


@pytest.mark.slow
@pytest.mark.parametrize("lead_s", [0.2, 0.3])
async def test_a_100_mm_cruise_sends_runs_as_long_as_the_hold_back_and_each_in_time(
    mcu: VirtualMcu, lead_s: float
) -> None:
    async with klipper_machine(mcu, lead_time_s=lead_s) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        await asyncio.sleep(0.2)
        oid = backend.axes[0].oid
        first_command, first_block = len(mcu.commands), len(mcu.block_messages)
        await run_job(app, [f"G1 X100 F{SPEED_MM_S * 60:g}"])
        check_steps(app, mcu)
        runs = [p for _, name, p in mcu.commands[first_command:]
                if name == "queue_step" and p["oid"] == oid]
        move_blocks = mcu.block_messages[first_block:]
        blocks = len(move_blocks)
        cruise_ticks = mcu.clock_hz / (SPEED_MM_S * STEPS_PER_MM)  # 9,000 at 72 MHz
        cruise = [p["count"] for p in runs
                  if p["add"] == 0 and abs(p["interval"] - cruise_ticks) < 0.01 * cruise_ticks]
        # every run of the cruise spans the hold-back at least (but the last: the deceleration
        # ends it); the first, the hold-back less the share at least (what turns within the
        # share after a sample leaves at it: the acceleration's last run takes it along)
        hold_back_steps = backend.hold_back_s * SPEED_MM_S * STEPS_PER_MM  # 1,200 (400)
        share_steps = max(backend.flush_s, SHARE_OF_HOLD_BACK * backend.hold_back_s) * (
            SPEED_MM_S * STEPS_PER_MM)
        assert cruise and min(cruise[1:-1]) >= 0.95 * hold_back_steps, cruise
        assert cruise[0] >= 0.95 * (hold_back_steps - share_steps), cruise
        cruise_s = (100.0 - SPEED_MM_S ** 2 / ACCEL_MM_S2) / SPEED_MM_S  # 0.967 s
        most_cruise = math.ceil(cruise_s / backend.hold_back_s)  # 20 (~16 at 20 ms flushes)
        assert len(cruise) <= most_cruise + 1, cruise
        # the ramps: about eight runs each (as Klipper's stepcompress finds for them)
        assert len(runs) <= len(cruise) + 2 * 10, [(p["interval"], p["count"], p["add"])
                                                   for p in runs]
        # a block for each cruise run, two or three for each ramp (its runs span two or three
        # flushes), and the polls before and after the move, alone
        assert blocks <= len(cruise) + 2 * 3 + 3, (blocks, len(cruise))
        # the clock is polled every 0.4 s in motion, and the polls ride in the steps' blocks
        polls = [names for names in move_blocks if "get_clock" in names]
        assert len(polls) >= 2, move_blocks
        # while steps flow (between the first and the last block with steps) the polls ride
        # (one may miss its block when the loop is late on a loaded machine); before and after,
        # nothing moves and a poll cannot ride (how many: the load decides)
        with_steps = [i for i, names in enumerate(move_blocks) if "queue_step" in names]
        flowing = move_blocks[with_steps[0]:with_steps[-1] + 1]
        assert flowing.count(["get_clock"]) <= 1, polls
        assert any("queue_step" in names for names in polls), polls
        # each run left at least the stall ride-through (lead - hold-back - flush, 130 ms)
        # ahead of its first step, half of it on a loaded machine
        ride_through_s = backend.lead_s - backend.hold_back_s - backend.flush_s
        assert ride_through_s == pytest.approx(0.13)
        stepper = mcu.steppers[oid]
        ahead_s = min((int(r.clocks[0]) - r.received_clock) / mcu.clock_hz
                      for r in stepper.runs if len(r.clocks))
        assert ahead_s >= 0.5 * ride_through_s, ahead_s
