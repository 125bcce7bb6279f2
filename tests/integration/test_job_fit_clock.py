"""A job is checked against the travel from where it is placed before anything moves, and its
remaining time is read from what has not executed (virtual clock)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from server.app import App
from server.errors import CommandError
from server.jobs.jobs import JobProgress
from tests.conftest import make_config
from tests.support.helpers import running, submit_all

NEGATIVE_Y = b"G21 G90\nG0 X0 Y0\nG1 X50 Y-20 F600\nG1 X0 Y0\n"  # origin top-left, Y down


def config_in(tmp_path: Path, **sections: Any) -> Any:
    return make_config(jobs={"data_dir": str(tmp_path)}, **sections)


def progress(app: App) -> JobProgress:
    value = app.kernel.jobs.progress()
    assert value is not None
    return value


async def sleep(app: App, seconds: float) -> None:
    await app.clock.sleep(seconds)  # type: ignore[attr-defined]


async def test_a_job_that_does_not_fit_is_refused_naming_axis_overshoot_and_origin(
    tmp_path: Path,
) -> None:
    async with running(config_in(tmp_path)) as app:
        await app.kernel.jobs.save("neg.nc", NEGATIVE_Y)
        with pytest.raises(CommandError) as info:
            await app.kernel.jobs.start("neg.nc")
        assert info.value.code == 47
        message = info.value.message
        assert "Y: 20.000 mm below the travel's minimum" in message
        assert "Y work origin between 20.000 and 300.000" in message
        assert "X:" not in message, "X fits"
        assert app.kernel.jobs.progress() is None and not app.kernel.jobs.running
        assert app.kernel.machine.stepgen.state.position_mm == (0.0, 0.0, 0.0)
        with pytest.raises(CommandError) as played:
            await submit_all(app, ["play neg.nc"])  # Smoothie's play: the same check
        assert played.value.code == 47


async def test_a_job_placed_by_its_work_origin_fits_and_runs_there(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        await app.kernel.jobs.save("neg.nc", NEGATIVE_Y)
        await submit_all(app, ["G0 X100 Y150", "G10 L20 P1 X0 Y0"])
        await app.kernel.machine.wait_idle()
        await submit_all(app, ["G53 G0 X300 Y250"])  # the head away from the job
        await app.kernel.machine.wait_idle()
        plan = await app.kernel.jobs.plan("neg.nc")
        assert (plan.fit.extent_min_mm, plan.fit.extent_max_mm) == (
            (100.0, 130.0, 0.0), (150.0, 150.0, 0.0)), "the job's extent, not where the head is"
        started = await app.kernel.jobs.start("neg.nc")
        assert started.fit is not None and started.fit["fits"]
        assert started.fit["extent_min_mm"] == {"X": 100.0, "Y": 130.0, "Z": 0.0}
        await app.kernel.jobs._task  # noqa: SLF001 - wait for the player
        assert progress(app).state == "done"
        assert app.kernel.machine.stepgen.state.position_mm == (100.0, 150.0, 0.0)  # G0 X0 Y0


async def test_the_estimate_starts_from_the_machine_position_and_offsets(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        await app.kernel.jobs.save("rel.nc", b"G91 G1 X100 F600\n")  # 10 s from anywhere
        await submit_all(app, ["G0 X250 Y10"])
        await app.kernel.machine.wait_idle()
        job = await app.kernel.jobs.start("rel.nc")
        assert job.estimate_s is not None and 10.0 <= job.estimate_s < 10.2
        await app.kernel.jobs._task  # noqa: SLF001
        assert app.kernel.machine.stepgen.state.position_mm == (350.0, 10.0, 0.0)


async def test_remaining_time_stands_still_in_a_hold_and_falls_faster_at_150_percent(
    tmp_path: Path,
) -> None:
    async with running(config_in(tmp_path)) as app:
        await app.kernel.jobs.save("long.nc", b"G1 X300 F600\n")  # 30 s at 10 mm/s
        job = await app.kernel.jobs.start("long.nc")
        assert job.estimate_s is not None and 30.0 <= job.estimate_s < 30.2
        await sleep(app, 5.0)
        at_5s = progress(app).remaining_s
        assert at_5s is not None and 24.5 < at_5s < 25.7
        app.kernel.control.hold()
        await sleep(app, 0.5)  # decelerating
        held = progress(app).remaining_s
        assert progress(app).state == "paused" and progress(app).paused_for == "hold"
        await sleep(app, 3.0)
        assert progress(app).remaining_s == held, "a held job's clock stands still"
        app.kernel.control.resume()
        await sleep(app, 2.0)
        before = progress(app).remaining_s
        assert before is not None
        app.kernel.machine.set_overrides(feed=150)
        await sleep(app, 2.0)
        after = progress(app).remaining_s
        assert after is not None
        assert before - after > 2.0 * 1.5, "the remaining work goes at 150 %"
        assert after == pytest.approx((before - 2.0 * 1.5) / 1.5, abs=0.3)


async def test_an_aborted_or_failed_job_shows_no_remaining_time(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        jobs = app.kernel.jobs
        await jobs.save("long.nc", b"G1 X300 F600\n")
        await jobs.save("bad.nc", b"G1 X10 F600\nG42\n")
        await jobs.start("long.nc")
        await sleep(app, 1.0)
        assert progress(app).remaining_s is not None
        jobs.abort()
        assert (progress(app).state, progress(app).remaining_s) == ("aborted", None)
        await submit_all(app, ["G0 X0"])
        await app.kernel.machine.wait_idle()
        await jobs.start("bad.nc")
        await jobs._task  # noqa: SLF001
        assert (progress(app).state, progress(app).remaining_s) == ("failed", None)


@pytest.mark.parametrize(
    ("stop", "reason"), [("M0", "M0"), ("M1", "M1"), ("T2 M6", "tool change T2")])
async def test_m0_m1_and_m6_pause_the_job_until_resumed(
    tmp_path: Path, stop: str, reason: str
) -> None:
    async with running(config_in(tmp_path)) as app:
        jobs = app.kernel.jobs
        await jobs.save("stop.nc", f"G1 X10 F600\n{stop}\nG1 X20\n".encode())
        await jobs.start("stop.nc")
        await sleep(app, 3.0)
        assert (progress(app).state, progress(app).paused_for) == ("paused", reason)
        assert app.kernel.machine.stepgen.state.position_mm[0] == pytest.approx(10.0, abs=1e-3)
        await sleep(app, 2.0)
        assert app.kernel.machine.stepgen.state.position_mm[0] == pytest.approx(10.0, abs=1e-3)
        app.kernel.control.resume()  # the UI's Continue, or ~
        await jobs._task  # noqa: SLF001
        assert progress(app).state == "done"
        assert app.kernel.machine.stepgen.state.position_mm[0] == 20.0


async def test_a_finished_job_says_how_long_it_ran(tmp_path: Path) -> None:
    """``[MSG:job NAME done in …]`` carries the job's real run time (it said 0.00s when no
    client had asked for the progress while it ran). 50 mm at 10 mm/s: a little over 5 s."""
    async with running(config_in(tmp_path)) as app:
        pushed: list[str] = []
        app.kernel.events.subscribe("push", pushed.append)
        await app.kernel.jobs.save("line.nc", b"G21 G90\nG1 X50 F600\n")
        await app.kernel.jobs.start("line.nc")
        for _ in range(40):  # (not asking for the progress: that brought the time up to date)
            await sleep(app, 0.5)
            if done := [line for line in pushed if " done in " in line]:
                break
    assert len(done) == 1, pushed
    seconds = float(done[0].rpartition(" done in ")[2].rstrip("s]"))
    assert 5.0 <= seconds < 6.0, done
