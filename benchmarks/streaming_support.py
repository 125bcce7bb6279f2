"""What the streaming benchmark drives the server with: its config, the event loops to compare,
the client processes (the streaming client and the ``?`` probe) and a garbage-collector watch.

Both clients run in their own processes (:mod:`benchmarks.stream_client`,
:mod:`benchmarks.status_probe`), so the server's event loop is shared with neither.
"""

from __future__ import annotations

import asyncio
import gc
import importlib.util
import json
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from benchmarks.common import scratch_data_dir
from benchmarks.stream_client import HOST
from server.cli.main import loop_factory
from server.config import Config, StepgenConfig
from server.config_loader import build_config
from server.runtime import realtime

CLIENT = Path(__file__).resolve().with_name("stream_client.py")
PROBE = Path(__file__).resolve().with_name("status_probe.py")
PROBE_PERIOD_MS = 10.0  # the second client asks `?` at 100 Hz
T = TypeVar("T")


def bench_config() -> Config:
    """A laser machine fast enough for any raster; soft limits off (the corpus is foreign)."""
    axis = {"max_rate_mm_s": 10000.0, "accel_mm_s2": 50000.0, "min_mm": -100000.0,
            "max_mm": 100000.0}
    return build_config({
        "machine": {"soft_limits": False, "laser_mode": True},
        "axes": {"x": {"steps_per_mm": 80.0, **axis}, "y": {"steps_per_mm": 80.0, **axis},
                 "z": {"steps_per_mm": 400.0, **axis}},
        "tcp": {"host": HOST, "port": 0},
        "jobs": {"data_dir": scratch_data_dir()},
    }, "bench_streaming")


# -- event loops -----------------------------------------------------------------------------------
REALTIME = "+rt"  # a loop name's suffix: its thread at the real-time priority `serve` asks for


def may_run_realtime() -> bool:
    """Whether this process may give a thread real-time priority (``motiond serve``'s default)."""
    return realtime.allowed(StepgenConfig().realtime_priority)


def loop_names() -> list[str]:
    """The configurations to measure side by side: asyncio's loop at ordinary priority; as
    ``motiond serve`` runs it (real-time priority, when this process may have it); uvloop's
    when installed (``serve`` gives it no real-time priority: see server/runtime/realtime.py)."""
    rt = may_run_realtime()
    names = ["asyncio"] + [f"asyncio{REALTIME}"] * rt
    return names + ["uvloop"] * (importlib.util.find_spec("uvloop") is not None)


def default_loop_name() -> str:
    """The configuration ``motiond serve`` runs with its default config (``--loop auto``)."""
    if may_run_realtime():
        return f"asyncio{REALTIME}"
    return "uvloop" if importlib.util.find_spec("uvloop") is not None else "asyncio"


def run_on(loop: str, work: Callable[[], Awaitable[T]]) -> T:
    """Run ``work()`` on a new event loop of that name, as ``motiond serve --loop`` would: with a
    ``+rt`` suffix, its thread at ``[stepgen] realtime_priority``'s default for the run."""
    name, rt, _ = loop.partition(REALTIME)
    switch_interval_s = sys.getswitchinterval()
    priority = realtime.claim(StepgenConfig().realtime_priority if rt else 0)
    try:
        with asyncio.Runner(loop_factory=loop_factory(name)) as runner:
            return runner.run(work())  # type: ignore[arg-type]
    finally:
        if priority.realtime:
            realtime.release(switch_interval_s)


# -- the client processes --------------------------------------------------------------------------
async def run_client(port: int, path: Path, *, banner: bool, check: bool = False) -> dict[str, Any]:
    """Stream ``path`` with character counting from a client process; its figures."""
    args = [sys.executable, str(CLIENT), str(port), str(path)]
    args += ["--banner"] * banner + ["--check"] * check
    process = await asyncio.create_subprocess_exec(*args, stdout=asyncio.subprocess.PIPE)
    stdout, _ = await process.communicate()
    if process.returncode != 0:
        raise RuntimeError(f"the client failed ({process.returncode})")
    result: dict[str, Any] = json.loads(stdout.decode().strip().splitlines()[-1])
    return result


class StatusProbe:
    """A second client process polling ``?`` at 100 Hz (:mod:`benchmarks.status_probe`)."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self._process = process

    @classmethod
    async def start(cls, port: int) -> StatusProbe:
        """Connect it and wait until it polls."""
        process = await asyncio.create_subprocess_exec(
            sys.executable, str(PROBE), str(port), "--period-ms", str(PROBE_PERIOD_MS),
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE)
        assert process.stdout is not None
        if (await process.stdout.readline()).strip() != b"ready":
            raise RuntimeError("the status probe did not start")
        return cls(process)

    def begin(self) -> None:
        """Count round trips from now on only."""
        assert self._process.stdin is not None
        self._process.stdin.write(b"start\n")

    async def finish(self) -> dict[str, float]:
        """Stop it; the round trips' count, p50/p99/max (ms) and misses."""
        stdout, _ = await self._process.communicate(b"")  # closes its standard input
        summary: dict[str, float] = json.loads(stdout.decode().strip().splitlines()[-1])
        return summary


# -- garbage collections ---------------------------------------------------------------------------
@dataclass(slots=True)
class GcWatch:
    """Counts this process's garbage collections per generation, and the longest, while on."""

    collections: list[int] = field(default_factory=lambda: [0, 0, 0])
    longest_s: float = 0.0
    _started_s: float = 0.0
    _on: bool = False

    def __enter__(self) -> GcWatch:
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *_: object) -> None:
        gc.callbacks.remove(self._callback)

    def switch(self, on: bool) -> None:
        self._on = on

    def _callback(self, phase: str, info: dict[str, int]) -> None:
        if not self._on:
            return
        if phase == "start":
            self._started_s = time.perf_counter()
            return
        self.collections[info["generation"]] += 1
        self.longest_s = max(self.longest_s, time.perf_counter() - self._started_s)
