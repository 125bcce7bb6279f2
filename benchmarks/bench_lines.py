"""The host's cost per G-code line: the Klipper benchmark's raster streamed into motiond.

``python -m server.cli`` on the simulated machine (the laser module on its simulated output;
the same axes, limits and cornering as the Klipper benchmark's) gets the raster job of
:mod:`benchmarks.klipper_rig_jobs` (20 mm lines of 0.1 mm segments at F6000, ~1,000 lines a
second of motion) from the streaming benchmark's client process, character counting over TCP,
in real time. Reported per run: the server process's CPU (every thread's, from ``/proc``) per
line and per second of motion, from the first line sent to idle at the job's end. The simulated
machine's own tick is in the figure (as the Klipper backend's is on the rig); a job this dense
spends most of it on the lines' path: transport, session, dispatcher, interpreter, planner and
the step generator's popping of blocks.

Run: ``python -m benchmarks lines [--quick] [--runs N] [--motiond-tree DIR]`` (``--motiond-tree``:
measure another checkout, e.g. main's, in the same minutes).
"""

from __future__ import annotations

import asyncio
import contextlib
import statistics
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path

from benchmarks.common import REPO, BenchResult
from benchmarks.klipper_rig_hosts import (
    ACCEL_MM_S2,
    JUNCTION_DEVIATION_MM,
    LASER_S_MAX,
    MAX_RATE_MM_S,
    STEPS_PER_MM,
    TRAVEL_MM,
    Motiond,
    cpu_ns,
)
from benchmarks.klipper_rig_jobs import Job, raster


def sim_toml(data_dir: Path) -> str:
    axes = "".join(f"[axes.{a}]\nsteps_per_mm = {STEPS_PER_MM}\nmax_rate_mm_s = {MAX_RATE_MM_S}\n"
                   f"accel_mm_s2 = {ACCEL_MM_S2}\nmax_mm = {TRAVEL_MM}\n" for a in "xy")
    return (f"[machine]\nlaser_mode = true\n{axes}[planner]\n"
            f"junction_deviation_mm = {JUNCTION_DEVIATION_MM}\n[jobs]\ndata_dir = '{data_dir}'\n"
            f"[http]\nenabled = false\n[laser]\nmaximum_s_value = {LASER_S_MAX}\n")


class Server(Motiond):
    """motiond on the simulated machine (the rig benchmark's host, without a rig)."""

    @classmethod
    @contextlib.asynccontextmanager
    async def start_sim(cls, workdir: Path, tree: Path) -> AsyncIterator[Server]:
        async with cls.serving(sim_toml(workdir / "data"), workdir, tree) as server:
            yield server


def one_move(job: Job) -> Job:
    """The raster's seconds of motion in one move with the laser on (the tick's cost, and
    nearly none of the lines'): as long as the raster takes at the same acceleration."""
    seconds = job.moves["x"][0].duration_s * len(job.moves["x"]) * 1.02
    feed_mm_s = 100.0 / (seconds - 100.0 / 2000.0)  # 100 mm: cruise plus one ramp's time
    x, y = job.start[0] + 100.0, job.start[1]
    return Job("one move", job.start, (x, y), motiond=[
        f"M3 S{LASER_S_MAX * 0.8:.0f} G1 X{x:.3f} F{feed_mm_s * 60:.1f}", "M5"])


async def measure(jobs: list[Job], runs: int, tree: Path) -> list[list[tuple[float, float]]]:
    """(CPU seconds, wall seconds) of each run of each job, from the first line to idle; the
    jobs run in turn, run after run."""
    figures: list[list[tuple[float, float]]] = [[] for _ in jobs]
    with tempfile.TemporaryDirectory(prefix="motiond-bench-lines-") as name:
        async with Server.start_sim(Path(name), tree) as server:
            for _ in range(runs):
                for job, out in zip(jobs, figures, strict=True):
                    await server.run([f"G0 X{job.start[0]} Y{job.start[1]}"], job.start)
                    cpu0, wall0 = cpu_ns(server.process.pid), time.monotonic()
                    await server.run(job.lines("motiond"), job.end)
                    cpu1, wall1 = cpu_ns(server.process.pid), time.monotonic()
                    out.append(((cpu1 - cpu0) / 1e9, wall1 - wall0))
    return figures


def run(quick: bool, runs: int | None = None, motiond_tree: Path | None = None) -> BenchResult:
    result = BenchResult("lines", quick)
    tree = (motiond_tree or REPO).resolve()
    job = raster(lines=6 if quick else 12)
    count = len(job.motiond) + 1
    figures, single = asyncio.run(measure([job, one_move(job)], runs or (2 if quick else 5),
                                          tree))
    per_s = [cpu_s / wall_s for cpu_s, wall_s in figures]
    tick_s = [cpu_s / wall_s for cpu_s, wall_s in single]
    per_line_us = [cpu_s / count * 1e6 for cpu_s, _ in figures]
    # each run less the single move's CPU per second of the same run, over the lines
    net_us = [(cpu_s - tick * wall_s) / count * 1e6
              for (cpu_s, wall_s), tick in zip(figures, tick_s, strict=True)]
    print(f"motiond from {tree}, simulated machine; raster: {count:,} lines over TCP "
          f"(character counting), {len(figures)} runs")
    rows = [("raster: CPU per s of motion (s/s)", per_s, "7.3f"),
            ("one move: CPU per s (s/s)", tick_s, "7.3f"),
            ("raster: wall (s)", [w for _, w in figures], "7.2f"),
            ("CPU per line (µs)", per_line_us, "7.1f"),
            ("CPU per line less the tick (µs)", net_us, "7.1f")]
    for label, values, form in rows:
        print(f"   {label:36}" + " ".join(f"{v:{form}}" for v in values))
    median = statistics.median
    print(f"   median {median(per_line_us):.1f} µs a line, {median(net_us):.1f} µs less the "
          f"tick; {median(per_s):.3f} s/s")
    result.add("raster", str(tree), lines=(count, "lines"),
               cpu_per_line=(median(per_line_us), "µs"),
               cpu_per_line_net=(median(net_us), "µs"),
               cpu_per_motion_s=(median(per_s), "s/s"),
               cpu_one_move=(median(tick_s), "s/s"),
               wall=(median(w for _, w in figures), "s"))
    return result
