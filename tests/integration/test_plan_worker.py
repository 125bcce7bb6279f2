"""The plan worker (:class:`~server.jobs.planning.PlanWorker`): one planning process kept
between plans, so a job's plan is read warm, not by a fresh child each time; a cancel kills it
at once and the next plan starts another; it ends with the server, or when idle."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

from benchmarks.bench_plan import write_raster
from server.cli.offline import machine_interpreter
from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.jobs import planning
from server.jobs.clock import JobPlan
from server.jobs.planning import IN_THREAD_BYTES, JobPlans, PlanWorker
from tests.conftest import make_config


def slow_reader(path: Path, core: CoreConfig, interpreter: Interpreter,
                stopped: Callable[[], bool]) -> str:
    """A plan that takes far longer than any test waits (read in the worker)."""
    time.sleep(60)
    return "late"


def quick_reader(path: Path, core: CoreConfig, interpreter: Interpreter,
                 stopped: Callable[[], bool]) -> str:
    return path.name


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


async def ended(pid: int) -> bool:
    """Whether process ``pid`` is gone (or a zombie) within a second."""
    for _ in range(20):
        if not alive(pid):
            return True
        await asyncio.sleep(0.05)
    return False


async def test_plans_one_after_another_are_read_by_one_process(tmp_path: Path) -> None:
    config = make_config()
    plans, pids = JobPlans(lambda plan: None), []
    try:
        for index, lines in enumerate((1200, 900, 100)):  # the last: a small job's file
            path = tmp_path / f"job{index}.nc"
            write_raster(path, lines)
            size = path.stat().st_size
            assert (size <= IN_THREAD_BYTES) == (index == 2)
            plan = await plans.plan(path, config.core, machine_interpreter(config), object(),
                                    size)
            assert isinstance(plan, JobPlan) and plan.lines == lines and plan.fit.fits
            assert plan.timing is not None and plan.timing.duration_s > 0.0
            worker = plans._worker  # noqa: SLF001
            assert worker.running and worker._process is not None  # noqa: SLF001
            pids.append(worker._process.pid)  # noqa: SLF001
        assert len(set(pids)) == 1, "the same warm process read each plan, the small one too"
    finally:
        await plans.close()
    assert await ended(pids[0]), "it ends with the plans' owner"


async def test_a_cancel_kills_the_worker_at_once_and_the_next_plan_starts_another(
    tmp_path: Path
) -> None:
    config = make_config()
    interpreter = machine_interpreter(config)
    worker = PlanWorker()
    try:
        path = tmp_path / "job.nc"
        path.write_text("G1 X1\n")
        first = worker.plan(quick_reader, path, config.core, interpreter)
        assert await first.result() == "job.nc"
        assert worker._process is not None  # noqa: SLF001
        pid = worker._process.pid  # noqa: SLF001
        slow = worker.plan(slow_reader, path, config.core, interpreter)
        reading = asyncio.ensure_future(slow.result())
        await asyncio.sleep(0.5)
        assert not reading.done() and worker.busy and alive(pid), reading
        asked_s = time.perf_counter()
        slow.cancel()
        assert await asyncio.wait_for(reading, 5.0) is None
        assert time.perf_counter() - asked_s < 1.0
        assert await ended(pid), "the plan's process was ended"
        again = worker.plan(quick_reader, path, config.core, interpreter)
        assert await again.result() == "job.nc"
        assert worker._process is not None and worker._process.pid != pid  # noqa: SLF001
    finally:
        worker.close()


async def test_an_error_in_the_worker_is_raised_where_the_plan_is_awaited(
    tmp_path: Path
) -> None:
    config = make_config()
    worker = PlanWorker()
    try:
        plan = worker.plan(planning.read_plan, tmp_path / "gone.nc", config.core,
                           machine_interpreter(config))
        try:
            await plan.result()
        except OSError as exc:
            assert "gone.nc" in str(exc)
        else:
            raise AssertionError("a missing file raises")
        assert worker.running, "the worker reads the next plan"
    finally:
        worker.close()


async def test_an_idle_worker_ends_by_itself_and_one_that_died_is_replaced(
    tmp_path: Path
) -> None:
    config = make_config()
    interpreter = machine_interpreter(config)
    path = tmp_path / "job.nc"
    path.write_text("G1 X1\n")
    worker = PlanWorker(idle_s=0.3)
    try:
        assert await worker.plan(quick_reader, path, config.core, interpreter).result() == "job.nc"
        assert worker._process is not None  # noqa: SLF001
        idle_pid = worker._process.pid  # noqa: SLF001
        assert await ended(idle_pid), "idle: it ended by itself (its memory back to the host)"
        assert await worker.plan(quick_reader, path, config.core, interpreter).result() == "job.nc"
        assert worker._process is not None  # noqa: SLF001
        killed_pid = worker._process.pid  # noqa: SLF001
        assert killed_pid != idle_pid
        os.kill(killed_pid, signal.SIGKILL)  # dies between plans, unknown to the server
        assert await worker.plan(quick_reader, path, config.core, interpreter).result() == "job.nc"
        assert worker._process is not None and worker._process.pid != killed_pid  # noqa: SLF001
    finally:
        worker.close()
