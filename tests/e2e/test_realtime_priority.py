"""The event loop's thread asks for real-time scheduling; what it starts runs at ordinary
priority, and a refusal is reported, never raised (server/runtime/realtime.py)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from server.runtime import realtime
from tests.conftest import REPO
from tests.support.processes import motiond

T = TypeVar("T")


def in_thread(work: Callable[[], T]) -> T:
    """Run ``work`` in a fresh thread (the test runner's own thread keeps its policy)."""
    result: list[T] = []
    thread = threading.Thread(target=lambda: result.append(work()))
    thread.start()
    thread.join()
    return result[0]


def test_the_loop_thread_runs_fifo_and_what_it_starts_runs_ordinary() -> None:
    def claim_and_look() -> tuple[realtime.Priority, int, int, str]:
        before = sys.getswitchinterval()
        priority = realtime.claim(7)
        try:
            mine = os.sched_getscheduler(0)
            worker = in_thread(lambda: os.sched_getscheduler(0))
            child = subprocess.run(
                [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                capture_output=True, text=True, check=True,
            ).stdout.strip()
            return priority, mine, worker, child
        finally:
            realtime.release(before)

    priority, mine, worker, child = in_thread(claim_and_look)
    assert priority.realtime and priority.priority == 7, priority.detail
    assert mine & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
    assert worker == os.SCHED_OTHER  # a worker thread (to_thread) never competes with the loop
    assert child == str(os.SCHED_OTHER)  # nor does a process it starts


def test_priority_zero_leaves_the_thread_ordinary() -> None:
    priority = in_thread(lambda: realtime.claim(0))
    assert not priority.realtime
    assert "realtime_priority = 0" in priority.detail


def test_without_the_right_it_runs_ordinary_and_says_how_to_grant_it() -> None:
    script = (
        "import os, sys\n"
        "from server.runtime import realtime\n"  # imported first: nobody cannot read /root
        "os.setgroups([]); os.setgid(65534); os.setuid(65534)\n"  # nobody: no CAP_SYS_NICE
        "p = realtime.claim(10)\n"
        "print(p.priority, os.sched_getscheduler(0)); print(p.detail)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, check=True)
    numbers, detail = done.stdout.splitlines()
    assert numbers == f"0 {os.SCHED_OTHER}"
    assert "refused" in detail and "cap_sys_nice" in detail
    assert "realtime_priority = 0" in detail


async def test_motiond_serve_runs_its_loop_fifo_unless_told_not_to(tmp_path: Path) -> None:
    (tmp_path / "rt").mkdir()
    (tmp_path / "off").mkdir()
    async with motiond(tmp_path / "rt") as served:
        policy = os.sched_getscheduler(served.process.pid)  # the main thread: the loop's
        assert policy & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
        assert os.sched_getparam(served.process.pid).sched_priority == 10  # the default
    async with motiond(tmp_path / "off", "[stepgen]\nrealtime_priority = 0\n") as served:
        assert os.sched_getscheduler(served.process.pid) == os.SCHED_OTHER


def test_no_real_time_priority_on_a_loop_other_than_asyncios() -> None:
    class OtherLoop(asyncio.AbstractEventLoop):  # uvloop's Loop is not a BaseEventLoop either
        pass

    def claim_on_other() -> tuple[realtime.Priority, int]:
        priority = realtime.claim_for(OtherLoop(), 10)
        return priority, os.sched_getscheduler(0)

    priority, policy = in_thread(claim_on_other)
    assert not priority.realtime and "OtherLoop" in priority.detail
    assert policy == os.SCHED_OTHER


async def test_asyncios_loop_gets_it() -> None:
    def claim_on_asyncio() -> realtime.Priority:
        loop = asyncio.new_event_loop()
        try:
            return realtime.claim_for(loop, 3)
        finally:
            loop.close()

    before = sys.getswitchinterval()
    try:
        assert in_thread(claim_on_asyncio).priority == 3
    finally:
        sys.setswitchinterval(before)
