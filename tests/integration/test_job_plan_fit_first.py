"""With a core to spare, a big job's fit is answered before its time, which is filled in
when the whole plan comes (read in processes of their own: :mod:`server.jobs.planning`)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from server.jobs import planning
from server.jobs.clock import read_plan
from tests.conftest import make_config
from tests.support.helpers import running

LINES = 200_000  # the whole plan: 1.1 s of CPU here, the fit alone 0.7 s


def write_short_segments(path: Path, count: int) -> None:
    """0.1 mm segments back and forth, the shortest lines (the plan's share is largest)."""
    lines = ["G21 G90 G1 F6000"] + [f"X{(i % 1000) * 0.1:.1f}" for i in range(1, count)]
    path.write_text("\n".join(lines) + "\n")


async def test_the_fit_answers_first_and_the_time_is_filled_in(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(planning, "TIMING_GRACE_S", 0.0)  # the fit answers as it comes
    async with running(make_config(jobs={"data_dir": str(tmp_path)})) as app:
        jobs = app.kernel.jobs
        jobs.path("big.nc").parent.mkdir(parents=True, exist_ok=True)
        write_short_segments(jobs.path("big.nc"), LINES)
        plan = await jobs.plan("big.nc")
        assert plan.fit.fits and plan.lines == LINES
        assert plan.timing is None, "the fit did not wait for the time"
        for _ in range(2400):  # up to 2 minutes on a busy host
            if plan.timing is not None:
                break
            await asyncio.sleep(0.05)
        interpreter = app.kernel.machine.new_interpreter(soft_limits=False, live=True)
        whole = await asyncio.to_thread(read_plan, jobs.path("big.nc"),
                                        app.kernel.config.core, interpreter, lambda: False)
        assert plan.timing is not None and whole.timing is not None
        assert plan.duration_s == whole.duration_s > 0.0, "the time of the whole plan"
        assert plan.fit == whole.fit, "the fit alone finds the extent the whole plan finds"
        assert await jobs.plan("big.nc") is plan, "kept, with its time"
