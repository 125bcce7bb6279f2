"""Streaming over TCP with Grbl character counting (128-byte window), side by side.

1. Throughput: the raster corpus file (laser-raster-tree.nc, ~54k lines) streamed to a bare
   asyncio server that answers ``ok`` to every line, then to motiond in check mode (``$C``:
   every line parsed and interpreted, nothing moves), in the same run. Prints lines/s for
   both and the ratio (target: motiond >= 0.3x the bare server), and the event loop's worst
   stall while motiond was streaming (goal: under 2 ms).
2. Real-time raster: 0.1 mm ``G1`` segments with alternating ``S`` values, streamed to motiond
   on the real clock at rising feeds. Execution time (first motion to idle) is compared with
   the offline estimate, which assumes a planner that never runs dry; once execution takes
   more than 2 % longer, the stream can no longer feed the machine (starvation). Prints
   segments/s per feed and the fastest sustained (target: 10,000 segments/s).

The streaming client (:mod:`benchmarks.stream_client`) runs in a subprocess (the server's
event loop is not shared with it), with a blocking socket and TCP_NODELAY; the same client
drives both servers.

Run: ``python -m benchmarks streaming [--quick] [--json]`` (quick: 1 s of motion per feed,
fewer repeats).
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if not __package__:  # run as a script (python benchmarks/bench_streaming.py): find the repo
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import CORPUS, BenchResult, standalone  # noqa: E402
from benchmarks.stream_client import HOST, WINDOW  # noqa: E402
from server.app import App  # noqa: E402
from server.config import Config, build_config  # noqa: E402
from server.offline.estimate import estimate  # noqa: E402
from server.runtime.clock import RealClock  # noqa: E402
from server.transports.tcp import TcpTransport  # noqa: E402

CLIENT = Path(__file__).resolve().with_name("stream_client.py")
RASTER_FILE = "laser-raster-tree.nc"
STARVED = 1.02  # execution longer than the estimate by more than 2 %: the planner ran dry
SEGMENT_MM = 0.1


def bench_config() -> Config:
    """A laser machine fast enough for any raster; soft limits off (the corpus is foreign)."""
    axis = {"max_rate_mm_s": 10000.0, "accel_mm_s2": 50000.0, "min_mm": -100000.0,
            "max_mm": 100000.0}
    return build_config({
        "machine": {"soft_limits": False, "laser_mode": True},
        "axes": {"x": {"steps_per_mm": 80.0, **axis}, "y": {"steps_per_mm": 80.0, **axis},
                 "z": {"steps_per_mm": 400.0, **axis}},
        "tcp": {"host": HOST, "port": 0},
    }, "bench_streaming")


# -- the client (stream_client.py, run as a script in a subprocess) -----------------------------
async def run_client(port: int, path: Path, *, banner: bool, check: bool = False) -> dict[str, Any]:
    args = [sys.executable, str(CLIENT), str(port), str(path)]
    args += ["--banner"] * banner + ["--check"] * check
    process = await asyncio.create_subprocess_exec(*args, stdout=asyncio.subprocess.PIPE)
    stdout, _ = await process.communicate()
    if process.returncode != 0:
        raise RuntimeError(f"the client failed ({process.returncode})")
    return json.loads(stdout.decode().strip().splitlines()[-1])


# -- 1. throughput against a bare server -----------------------------------------------------------
async def bare_ok_server(per_line: bool) -> asyncio.Server:
    """The baseline: answers ``ok`` to every line it receives, nothing else.

    ``per_line``: reads line by line (``readline``) and writes one ``ok`` per line, as a
    plain asyncio line server does; otherwise counts the newlines of each chunk it reads and
    answers them with one write (the least work a server can do per line).
    """

    async def serve_lines(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while await reader.readline():
            writer.write(b"ok\r\n")
            await writer.drain()
        writer.close()

    async def serve_chunks(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while data := await reader.read(65536):
            writer.write(b"ok\r\n" * data.count(b"\n"))
            await writer.drain()
        writer.close()

    return await asyncio.start_server(serve_lines if per_line else serve_chunks, HOST, 0)


def fastest(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return min(runs, key=lambda run: run["elapsed_s"])


async def bare_run(path: Path, per_line: bool, repeat: int) -> dict[str, Any]:
    server = await bare_ok_server(per_line)
    port = server.sockets[0].getsockname()[1]
    runs = [await run_client(port, path, banner=False) for _ in range(repeat)]
    server.close()
    await server.wait_closed()
    return fastest(runs)


async def motiond_runs(path: Path, repeat: int) -> tuple[list[dict[str, Any]], float]:
    """Stream ``path`` to motiond in check mode ``repeat`` times: each run with its worst
    event-loop stall, and the worst stall of the same server idle for 1 s before."""
    app = App(bench_config(), clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    await asyncio.sleep(0.2)
    app.kernel.loop_monitor.reset()
    await asyncio.sleep(1.0)
    idle_stall_s = app.kernel.loop_monitor.worst_stall_s
    runs = []
    for _ in range(repeat):
        app.kernel.loop_monitor.reset()
        run = await run_client(app.transports[0].port, path,  # type: ignore[attr-defined]
                               banner=True, check=True)
        runs.append({**run, "stall_s": app.kernel.loop_monitor.worst_stall_s})
    app.request_stop()
    await task
    return runs, idle_stall_s


async def throughput(result: BenchResult, repeat: int) -> None:
    path = CORPUS / RASTER_FILE
    bare_lines = await bare_run(path, True, repeat)
    bare_chunks = await bare_run(path, False, repeat)
    runs, idle_stall_s = await motiond_runs(path, repeat)
    motiond = fastest(runs)
    stall_s = motiond["stall_s"]

    rate_motiond = motiond["lines"] / motiond["elapsed_s"]
    print(f"\n1. {RASTER_FILE}: {motiond['lines']:,} lines, character counting, "
          f"{WINDOW}-byte window")
    print(f"   {'server':36} {'seconds':>8} {'lines/s':>9} {'errors':>7} {'motiond/this':>12}")
    for label, run in (("bare asyncio server, ok per line", bare_lines),
                       ("bare asyncio server, ok per chunk", bare_chunks),
                       ("motiond, check mode ($C)", motiond)):
        rate = run["lines"] / run["elapsed_s"]
        print(f"   {label:36} {run['elapsed_s']:8.2f} {rate:9,.0f} {run['errors']:7} "
              f"{rate_motiond / rate:11.2f}x")
        result.add("throughput", label, lines=(run["lines"], "lines"),
                   elapsed=(run["elapsed_s"], "s"), rate=(rate, "lines/s"),
                   errors=(run["errors"], "lines"), motiond_ratio=(rate_motiond / rate, "x"))
    ratio = rate_motiond / (bare_lines["lines"] / bare_lines["elapsed_s"])
    print(f"   ratio motiond / bare (ok per line): {ratio:.2f}x (target >= 0.30x) "
          f"{'OK' if ratio >= 0.3 else 'BELOW TARGET'}")
    print(f"   event loop worst stall while streaming: {stall_s * 1000:.2f} ms (goal < 2 ms) "
          f"{'OK' if stall_s < 0.002 else 'ABOVE GOAL'}; every run: "
          + " / ".join(f"{run['stall_s'] * 1000:.2f}" for run in runs) + " ms")
    print(f"   the same server idle for 1 s before: worst stall {idle_stall_s * 1000:.2f} ms "
          "(the machine's own noise)")
    print(f"   (best of {repeat} runs each; the client runs in its own process)")
    result.add("throughput", "summary", ratio_to_bare_per_line=(ratio, "x"),
               stall_streaming=(stall_s * 1000, "ms"), stall_idle=(idle_stall_s * 1000, "ms"),
               repeat=(repeat, "runs"))


# -- 2. the fastest raster sustained in real time ------------------------------------------------
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

    @property
    def ratio(self) -> float:
        return self.execution_s / self.estimate_s

    @property
    def segments_per_s(self) -> float:
        return self.segments / self.execution_s


async def raster_run(feed_mm_min: float, seconds: float, workdir: Path) -> RasterRun:
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
    loop = asyncio.get_running_loop()
    stepgen = app.kernel.machine.stepgen
    times: dict[str, float] = {}

    async def watch() -> None:  # first motion to idle, sampled every 0.5 ms
        while not stepgen.state.moving:  # noqa: ASYNC110 - a sampler, no event to wait on
            await asyncio.sleep(0.0005)
        times["start"] = loop.time()
        while stepgen.state.moving or not stepgen.idle or stepgen.state.blocks_done < segments:  # noqa: ASYNC110
            await asyncio.sleep(0.0005)
        times["end"] = loop.time()

    watcher = asyncio.create_task(watch())
    app.kernel.loop_monitor.reset()
    result = await run_client(app.transports[0].port, path, banner=True)  # type: ignore[attr-defined]
    await asyncio.wait_for(watcher, 30.0)
    stall_s = app.kernel.loop_monitor.worst_stall_s
    app.request_stop()
    await task
    if result["errors"]:
        raise RuntimeError(f"{result['errors']} lines refused at F{feed_mm_min:g}")
    return RasterRun(feed_mm_min, segments, planned.duration_s, times["end"] - times["start"],
                     stall_s)


async def realtime_raster(result: BenchResult, quick: bool, workdir: Path, repeat: int) -> None:
    feeds = [12_000, 30_000, 60_000, 90_000, 120_000, 180_000, 240_000, 300_000, 360_000,
             480_000]
    seconds = 1.0 if quick else 2.0
    print(f"\n2. real-time raster: {SEGMENT_MM} mm G1 segments, S alternating 100/900, "
          f"~{seconds:g} s of motion per feed, best of {repeat}")
    print(f"   {'feed mm/min':>11} {'segments':>9} {'estimate s':>10} {'executed s':>10} "
          f"{'exec/est':>8} {'segments/s':>10} {'loop stall':>10}")
    best: RasterRun | None = None
    for feed in feeds:
        runs = [await raster_run(feed, seconds, workdir) for _ in range(repeat)]
        run = min(runs, key=lambda r: r.ratio)
        starved = run.ratio > STARVED
        print(f"   {feed:11,} {run.segments:9,} {run.estimate_s:10.3f} {run.execution_s:10.3f} "
              f"{run.ratio:8.3f} {run.segments_per_s:10,.0f} {run.stall_s * 1000:8.2f}ms"
              + ("  starved" if starved else ""))
        record_raster(result, run, starved)
        if starved:
            break
        best = run
    if best is None:
        print("   no feed ran without starvation")
    else:
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
               stall=(run.stall_s * 1000, "ms"))


async def measure(quick: bool) -> BenchResult:
    result = BenchResult("streaming", quick)
    started = time.perf_counter()
    await throughput(result, repeat=2 if quick else 3)
    with tempfile.TemporaryDirectory() as workdir:
        await realtime_raster(result, quick, Path(workdir), repeat=1 if quick else 2)
    print(f"\n(total {time.perf_counter() - started:.0f} s)")
    return result


def run(quick: bool) -> BenchResult:
    return asyncio.run(measure(quick))


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
