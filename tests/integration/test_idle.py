"""An idle server sleeps: no tick, no laser sample, no switch check while nothing moves (on
real time), and the first line wakes everything exactly as before."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest

from server.backends.sim import SimBackend
from server.config_loader import load_config
from server.runtime.clock import RealClock
from tests.support.helpers import running, submit_all


def default_machine(tmp_path: Path) -> Any:
    """The embedded default (laser, endstops, air switch) with its own data folder."""
    config = load_config()
    config.core.jobs.data_dir = tmp_path
    return config


def counting(module: Any, method: str) -> list[int]:
    """Count the calls of ``module.method`` from now on."""
    calls = [0]
    original = getattr(module, method)

    def counted(*args: Any) -> Any:
        calls[0] += 1
        return original(*args)

    setattr(module, method, counted)
    return calls


async def test_nothing_ticks_while_idle_and_a_move_wakes_the_tick_the_laser_and_the_switches(
        tmp_path: Path) -> None:
    async with running(default_machine(tmp_path), RealClock()) as app:
        kernel = app.kernel
        backend = kernel.machine.backend
        assert isinstance(backend, SimBackend)
        await asyncio.sleep(0.2)  # start-up settles
        laser = counting(kernel.modules["laser"], "_sample")
        switches = counting(kernel.modules["endstops"], "triggered")
        ticks_before = len(backend.history)
        await asyncio.sleep(0.5)  # 500 ticks, samples and checks each at 1 kHz before
        assert len(backend.history) - ticks_before <= 2
        assert laser[0] <= 2 and switches[0] <= 2
        assert kernel.machine.stepgen.can_sleep

        assert await submit_all(app, ["G1 X20 F6000 M3 S500"]) == [[]]
        await asyncio.wait_for(kernel.machine.wait_idle(), 10)
        stepgen = kernel.machine.stepgen
        assert stepgen.state.position_mm[0] == pytest.approx(20.0)
        assert backend.steps[0] == 20 * 80  # every step, none lost across the sleep
        assert len(backend.history) - ticks_before > 10  # ticked while moving (late ticks merge)
        assert laser[0] > 100 and switches[0] > 100
        await asyncio.sleep(0.1)  # the laser lags the motion by up to one sample
        assert backend.output("laser") == 0.0  # laser mode: off once motion ends
        resting_from = laser[0]
        await asyncio.sleep(0.3)
        assert laser[0] - resting_from <= 2, "the sampler rests again"


async def test_a_hold_with_moves_queued_keeps_ticking_and_resumes(tmp_path: Path) -> None:
    async with running(default_machine(tmp_path), RealClock()) as app:
        machine = app.kernel.machine
        await submit_all(app, ["G1 X40 F6000"])
        await asyncio.sleep(0.1)
        app.kernel.control.hold()
        await asyncio.sleep(0.3)
        assert not machine.stepgen.can_sleep  # held with motion left: not idle
        app.kernel.control.resume()
        await asyncio.wait_for(machine.wait_idle(), 10)
        assert machine.stepgen.state.position_mm[0] == pytest.approx(40.0)


@pytest.mark.slow
async def test_the_klipper_backend_rests_while_idle_and_wakes_for_motion_outputs_and_faults(
        ) -> None:
    """The Klipper backend ticks only while it has steps queued, an output on or a fault to
    report: idle, the step generator sleeps; the next moves after a rest step exactly."""
    from server.backends.klipper.backend import KlipperBackend
    from tests.integration.test_klipper_backend import LASER, check_steps, run_job
    from tests.support.klipper_machine import klipper_machine
    from tests.support.virtual_mcu import VirtualMcu

    mcu = VirtualMcu(drift_ppm=40.0).start()
    try:
        async with klipper_machine(mcu, laser=LASER) as app:
            machine = app.kernel.machine
            backend = machine.backend
            assert isinstance(backend, KlipperBackend)
            await run_job(app, ["G1 X20 F6000"])
            samples = counting(backend, "sample")
            await asyncio.sleep(0.5)  # 500 ticks at 1 kHz if it still ticked
            assert samples[0] <= 5 and machine.stepgen.can_sleep

            await run_job(app, ["G1 X5 Y10 F6000", "G1 X30"])  # wakes; anchored afresh
            assert check_steps(app, mcu) > 0

            await submit_all(app, ["M3 S0", "M8"] if "air" in backend.outputs else ["M3 S0"])
            await submit_all(app, ["G1 X31 S300 F600"])  # laser on while it moves
            await asyncio.sleep(0.05)
            assert not machine.stepgen.can_sleep
            await machine.wait_idle()

            await asyncio.sleep(backend.lead_s + 0.3)
            resting = samples[0]
            await asyncio.sleep(0.3)
            assert samples[0] - resting <= 5, "rests again once the laser is off"
            mcu.mute()  # a fault while resting still becomes an alarm at once
            deadline = asyncio.get_running_loop().time() + 2.0
            while app.kernel.state.name != "ALARM":
                assert asyncio.get_running_loop().time() < deadline, "no alarm while resting"
                await asyncio.sleep(0.01)
    finally:
        mcu.stop()


async def test_the_loop_monitor_rides_the_ticks_and_keeps_its_own_timer_only_while_idle(
        tmp_path: Path) -> None:
    """While the step generator ticks, the monitor takes its samples from the ticks (no timer
    of its own: one wake-up less per tick); it still sees a stall; idle, its own timer runs."""
    async with running(default_machine(tmp_path), RealClock()) as app:
        monitor = app.kernel.loop_monitor
        await asyncio.sleep(0.2)  # start-up settles: nothing ticks
        assert not monitor.riding
        own_idle = monitor.own_samples
        await asyncio.sleep(monitor.quiet_period_s + 0.05)  # quiet: its slow period
        assert monitor.own_samples > own_idle, "idle, the monitor keeps its own timer"

        await submit_all(app, ["G1 X40 F3000"])  # 0.8 s of motion at 1 kHz ticks
        await asyncio.sleep(0.15)
        assert monitor.riding
        own, samples = monitor.own_samples, monitor.samples
        monitor.reset()
        await asyncio.sleep(0.2)
        end_s = time.thread_time() + 0.03
        while time.thread_time() < end_s:  # a callback that holds the loop: 30 ms of work
            pass
        await asyncio.sleep(0.2)
        assert monitor.own_samples - own <= 1, "no timer of its own while the ticks run"
        assert monitor.samples - samples > 50  # about 400 ticks (late ones merge)
        assert monitor.worst_stall_s >= 0.025  # the stall is seen through the ticks
        assert monitor.worst_cpu_stall_s >= 0.025  # ...and it was this thread's own work

        await asyncio.wait_for(app.kernel.machine.wait_idle(), 10)
        await asyncio.sleep(0.05)
        assert not monitor.riding
        own = monitor.own_samples
        await asyncio.sleep(0.1)
        assert monitor.own_samples > own, "its own timer runs again once the ticks stop"
