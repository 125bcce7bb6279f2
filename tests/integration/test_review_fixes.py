"""Regressions found in review: sleep, check mode, job control while held, shutdown, fire."""

from __future__ import annotations

import asyncio

import pytest

from server.errors import CommandError
from server.runtime.dispatcher import Dispatcher, SystemSource
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running, submit_all


async def test_sleep_locks_gcode_out_until_a_reset() -> None:
    async with running(make_config(laser={})) as app:
        await submit_all(app, ["$SLP"])
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["G1 X10 F600 M3 S1000"])
        assert info.value.code == 9
        assert app.kernel.machine.backend.output("laser") == 0.0
        app.kernel.machine.soft_reset()
        assert app.kernel.state is MachineState.IDLE
        assert await submit_all(app, ["G0 X1"]) == [[]]


async def test_a_reset_or_an_unlock_ends_check_mode() -> None:
    async with running(make_config()) as app:
        machine = app.kernel.machine
        await submit_all(app, ["$C"])
        machine.soft_reset()
        assert not machine.check_mode and app.kernel.state is MachineState.IDLE
        await submit_all(app, ["G0 X10"])
        await machine.wait_idle()
        assert machine.backend.steps[0] == 800, "moves run again after the reset"


async def test_suspend_resume_and_abort_are_answered_while_a_held_job_waits() -> None:
    async with running(make_config()) as app:
        jobs = app.kernel.jobs
        await jobs.save("long.nc", b"".join(b"G1 X%d F600\n" % (i % 2 * 100) for i in range(20)))
        jobs.play("long.nc")
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert await asyncio.wait_for(submit_all(app, ["suspend"]), 2) == [[]]
        await app.clock.sleep(2.0)  # type: ignore[attr-defined]
        assert app.kernel.state is MachineState.HOLD
        assert await asyncio.wait_for(submit_all(app, ["resume"]), 2) == [[]]
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert app.kernel.machine.stepgen.state.moving
        reply = await asyncio.wait_for(submit_all(app, ["abort"]), 2)
        assert reply == [["[MSG:Aborted playing or paused file]"]]
        assert not app.kernel.machine.stepgen.state.moving


async def test_a_job_stopped_by_an_alarm_is_failed_not_done() -> None:
    async with running(make_config()) as app:
        jobs = app.kernel.jobs
        await jobs.save("slow.nc", b"G1 X90 F60\n")
        jobs.play("slow.nc")
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        app.kernel.machine.emergency_stop()
        await asyncio.wait_for(jobs._task, 5)  # type: ignore[arg-type]  # noqa: SLF001
        progress = jobs.progress()
        assert progress is not None and progress.state == "failed"
        assert "alarm" in (progress.error or "")


@pytest.mark.slow
async def test_the_job_player_lets_other_tasks_run_on_lines_that_never_wait() -> None:
    async with running(make_config()) as app:
        jobs = app.kernel.jobs
        await jobs.save("modal.nc", b"G90 G21\n" * 30000)
        jobs.play("modal.nc")
        turns = 0
        while jobs.running:
            await asyncio.sleep(0)
            turns += 1
        assert jobs.progress().state == "done"  # type: ignore[union-attr]
        assert turns > 10, "the player yielded while streaming"


async def test_a_feed_hold_stops_a_focusing_fire() -> None:
    async with running(make_config(laser={})) as app:
        await submit_all(app, ["fire 50"])
        await app.clock.sleep(0.1)  # type: ignore[attr-defined]
        assert app.kernel.machine.backend.output("laser") > 0
        app.kernel.machine.feed_hold()
        assert app.kernel.machine.backend.output("laser") == 0.0


async def test_the_dispatcher_refuses_lines_after_shutdown_and_lines_overtaken_by_a_stop(
        ) -> None:
    stops = [0]
    dispatcher = Dispatcher(stops=lambda: stops[0])
    dispatcher.set_gcode_handler(lambda command: ["ran"])
    ticket = 0
    stops[0] += 1  # a stop after the line was sent
    with pytest.raises(CommandError):
        await dispatcher.submit("G0 X1", SystemSource(), ticket)
    assert await dispatcher.submit("G0 X1", SystemSource()) == ["ran"]
    dispatcher.close()
    with pytest.raises(CommandError) as info:
        await dispatcher.submit("G0 X1", SystemSource())
    assert info.value.code == 45
