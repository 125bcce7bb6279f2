"""Parts 2 and 3 of the streaming benchmark: rasters executed on the real clock.

A raster is 0.1 mm ``G1`` segments with ``S`` alternating 100/900, streamed to motiond with
character counting from a client process. Execution time (first motion to idle) is compared
with the offline estimate, which assumes a planner that never runs dry: once execution takes
more than 2 % longer, the stream could not feed the machine (starvation).

2. 20,000 segments/s on each event loop, side by side, while a second client process asks
   ``?`` at 100 Hz: the worst event-loop stall (wall, and the part of it this process spent
   running), the ``?`` round trip p50/p99/max, and garbage collections per second by generation.
3. rising feeds on the default event loop of ``motiond serve``: the fastest sustained rate.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.common import BenchResult
from benchmarks.streaming_support import GcWatch, StatusProbe, bench_config, run_client, run_on
from server.app import App
from server.offline.estimate import estimate
from server.runtime.clock import RealClock
from server.transports.tcp import TcpTransport

STARVED = 1.02  # execution longer than the estimate by more than 2 %: the planner ran dry
SEGMENT_MM = 0.1
STEADY_FEED_MM_MIN = 120_000  # 0.1 mm segments at 2,000 mm/s: 20,000 segments/s
GOAL_STALL_MS, GOAL_P99_MS, GOAL_MAX_MS = 2.0, 2.0, 4.0


def raster_lines(segments: int, feed_mm_min: float) -> list[str]:
    lines = ["G21 G90 M4 S0", f"G1 X{SEGMENT_MM:.1f} S100 F{feed_mm_min:g}"]
    lines += [f"X{i * SEGMENT_MM:.1f} S{100 + 800 * (i % 2)}" for i in range(2, segments + 1)]
    return lines + ["M5"]


@dataclass(slots=True)
class RasterRun:
    feed_mm_min: float
    segments: int
    estimate_s: float
    execution_s: float
    stall_s: float
    cpu_stall_s: float
    status: dict[str, float] = field(default_factory=dict)  # the `?` probe's summary
    gc_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gc_longest_s: float = 0.0

    @property
    def ratio(self) -> float:
        return self.execution_s / self.estimate_s

    @property
    def segments_per_s(self) -> float:
        return self.segments / self.execution_s


async def raster_run(feed_mm_min: float, seconds: float, workdir: Path,
                     probe: bool = False) -> RasterRun:
    """Stream and execute one raster on a fresh server; optionally with the ``?`` probe."""
    config = bench_config()
    segments = int(seconds * feed_mm_min / 60.0 / SEGMENT_MM)
    lines = raster_lines(segments, feed_mm_min)
    planned = estimate(lines, config.core)
    path = workdir / f"raster-{int(feed_mm_min)}.nc"
    path.write_text("\n".join(lines) + "\n")

    app = App(config, clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    await asyncio.sleep(0.2)
    port = app.transports[0].port  # type: ignore[attr-defined]
    status = await StatusProbe.start(port) if probe else None
    loop = asyncio.get_running_loop()
    stepgen, monitor = app.kernel.machine.stepgen, app.kernel.loop_monitor
    times: dict[str, float] = {}

    async def watch(gc_watch: GcWatch) -> None:  # first motion to idle, sampled every 0.5 ms
        while not stepgen.state.moving:  # noqa: ASYNC110 - a sampler, no event to wait on
            await asyncio.sleep(0.0005)
        times["start"] = loop.time()
        monitor.reset()
        gc_watch.switch(True)
        if status is not None:
            status.begin()
        while stepgen.state.moving or not stepgen.idle or stepgen.state.blocks_done < segments:  # noqa: ASYNC110
            await asyncio.sleep(0.0005)
        times["end"] = loop.time()
        gc_watch.switch(False)

    with GcWatch() as gc_watch:
        watcher = asyncio.create_task(watch(gc_watch))
        result = await run_client(port, path, banner=True)
        await asyncio.wait_for(watcher, 30.0)
    stall_s, cpu_stall_s = monitor.worst_stall_s, monitor.worst_cpu_stall_s
    summary = await status.finish() if status is not None else {}
    app.request_stop()
    await task
    if result["errors"]:
        raise RuntimeError(f"{result['errors']} lines refused at F{feed_mm_min:g}")
    execution_s = times["end"] - times["start"]
    per_s = tuple(count / execution_s for count in gc_watch.collections)
    return RasterRun(feed_mm_min, segments, planned.duration_s, execution_s, stall_s,
                     cpu_stall_s, summary, per_s, gc_watch.longest_s)  # type: ignore[arg-type]


# -- 2. 20,000 segments/s on each event loop, with a `?` poller ---------------------------------
def steady_rate(result: BenchResult, loops: list[str], quick: bool, workdir: Path,
                repeat: int) -> None:
    seconds = 1.0 if quick else 2.0
    print(f"\n2. real-time raster at 20,000 segments/s (F{STEADY_FEED_MM_MIN:,}, ~{seconds:g} s), "
          f"a second client asking ? at 100 Hz; {repeat} runs per event loop, interleaved")
    print(f"   {'loop':8} {'exec/est':>8} {'stall ms':>9} {'cpu stall':>9} {'? p50':>6} "
          f"{'? p99':>6} {'? max':>6} {'gc0/s':>6} {'gc1/s':>6} {'gc2/s':>6} {'gc max ms':>9}")
    runs: dict[str, list[RasterRun]] = {loop: [] for loop in loops}
    for _ in range(repeat):
        for loop in loops:
            run = run_on(loop, lambda: raster_run(STEADY_FEED_MM_MIN, seconds, workdir, True))
            runs[loop].append(run)
            status = run.status
            print(f"   {loop:8} {run.ratio:8.3f} {run.stall_s * 1000:9.2f} "
                  f"{run.cpu_stall_s * 1000:9.2f} {status['p50_ms']:6.2f} {status['p99_ms']:6.2f} "
                  f"{status['max_ms']:6.2f} " + " ".join(f"{r:6.1f}" for r in run.gc_per_s)
                  + f" {run.gc_longest_s * 1000:9.2f}")
    for loop, done in runs.items():
        summarise_steady(result, loop, done)


def summarise_steady(result: BenchResult, loop: str, runs: list[RasterRun]) -> None:
    def span(values: list[float]) -> str:
        return f"{min(values):.2f}-{max(values):.2f}"

    stalls = [r.stall_s * 1000 for r in runs]
    cpu_stalls = [r.cpu_stall_s * 1000 for r in runs]
    p99 = [r.status["p99_ms"] for r in runs]
    worst = [r.status["max_ms"] for r in runs]
    verdict = "OK" if (max(stalls) < GOAL_STALL_MS and max(p99) <= GOAL_P99_MS
                       and max(worst) <= GOAL_MAX_MS) else "ABOVE GOAL"
    print(f"   {loop}: stall {span(stalls)} ms (own work {span(cpu_stalls)} ms; goal < "
          f"{GOAL_STALL_MS:g}), ? p99 {span(p99)} ms (goal <= {GOAL_P99_MS:g}), max "
          f"{span(worst)} ms (goal <= {GOAL_MAX_MS:g}) {verdict}")
    for index, run in enumerate(runs):
        result.add("steady 20k segments/s", f"{loop} run {index + 1}",
                   executed_to_estimate=(run.ratio, "x"), stall=(run.stall_s * 1000, "ms"),
                   cpu_stall=(run.cpu_stall_s * 1000, "ms"),
                   status_p50=(run.status["p50_ms"], "ms"), status_p99=(run.status["p99_ms"], "ms"),
                   status_max=(run.status["max_ms"], "ms"),
                   status_missed=(run.status["missed"], "requests"),
                   gc0=(run.gc_per_s[0], "collections/s"), gc1=(run.gc_per_s[1], "collections/s"),
                   gc2=(run.gc_per_s[2], "collections/s"),
                   gc_longest=(run.gc_longest_s * 1000, "ms"))


# -- 3. the fastest raster sustained in real time ------------------------------------------------
def fastest_sustained(result: BenchResult, loop: str, quick: bool, workdir: Path,
                      repeat: int) -> None:
    feeds = [12_000, 30_000, 60_000, 90_000, 120_000, 180_000, 240_000, 300_000, 360_000,
             480_000]
    seconds = 1.0 if quick else 2.0
    print(f"\n3. real-time raster at rising feeds ({loop} event loop): {SEGMENT_MM} mm G1 "
          f"segments, ~{seconds:g} s of motion per feed, best of {repeat}")
    print(f"   {'feed mm/min':>11} {'segments':>9} {'estimate s':>10} {'executed s':>10} "
          f"{'exec/est':>8} {'segments/s':>10} {'loop stall':>10} {'cpu stall':>9}")
    best: RasterRun | None = None
    for feed in feeds:
        runs = [run_on(loop, lambda feed=feed: raster_run(feed, seconds, workdir))
                for _ in range(repeat)]
        run = min(runs, key=lambda r: r.ratio)
        starved = run.ratio > STARVED
        print(f"   {feed:11,} {run.segments:9,} {run.estimate_s:10.3f} {run.execution_s:10.3f} "
              f"{run.ratio:8.3f} {run.segments_per_s:10,.0f} {run.stall_s * 1000:8.2f}ms "
              f"{run.cpu_stall_s * 1000:7.2f}ms" + ("  starved" if starved else ""))
        record_raster(result, run, starved)
        if starved:
            break
        best = run
    if best is None:
        print("   no feed ran without starvation")
        return
    verdict = "OK" if best.segments_per_s >= 10_000 else "BELOW TARGET"
    print(f"   fastest sustained without starvation: {best.segments_per_s:,.0f} segments/s "
          f"at F{best.feed_mm_min:,.0f} (target 10,000) {verdict}")
    result.add("raster", "fastest sustained", feed=(best.feed_mm_min, "mm/min"),
               rate=(best.segments_per_s, "segments/s"))


def record_raster(result: BenchResult, run: RasterRun, starved: bool) -> None:
    result.add("raster", f"F{run.feed_mm_min:g}", note="starved" if starved else "",
               feed=(run.feed_mm_min, "mm/min"), segments=(run.segments, "segments"),
               estimate=(run.estimate_s, "s"), executed=(run.execution_s, "s"),
               executed_to_estimate=(run.ratio, "x"), rate=(run.segments_per_s, "segments/s"),
               stall=(run.stall_s * 1000, "ms"), cpu_stall=(run.cpu_stall_s * 1000, "ms"))
