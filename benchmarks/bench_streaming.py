"""Streaming over TCP with Grbl character counting (128-byte window), side by side.

1. Throughput: the raster corpus file (laser-raster-tree.nc, ~54k lines) streamed to a bare
   asyncio server that answers ``ok`` to every line, then to motiond in check mode (``$C``:
   every line parsed and interpreted, nothing moves) on each event loop (asyncio's, and
   uvloop's when installed), in the same run. Prints lines/s and the ratio to the bare server
   (target: motiond >= 0.6x, issue 41), and the event loop's worst stall while streaming
   (goal: under 2 ms), with the part of it this process spent running (the rest is the OS
   running others).
2. Real-time raster at 20,000 segments/s on each event loop while a second client asks ``?``
   at 100 Hz: worst stall, ``?`` round trip p50/p99/max, garbage collections per second.
3. Real-time raster at rising feeds: the fastest sustained rate (target: 10,000 segments/s).
   See :mod:`benchmarks.realtime_raster`.

The clients (:mod:`benchmarks.stream_client`, :mod:`benchmarks.status_probe`) run in their own
processes, with blocking sockets and TCP_NODELAY; the same client drives both servers.

Run: ``python -m benchmarks streaming [--quick] [--json]`` (quick: 1 s of motion per raster,
fewer repeats).
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if not __package__:  # run as a script (python benchmarks/bench_streaming.py): find the repo
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import CORPUS, BenchResult, standalone  # noqa: E402
from benchmarks.realtime_raster import fastest_sustained, steady_rate  # noqa: E402
from benchmarks.stream_client import HOST, WINDOW  # noqa: E402
from benchmarks.streaming_support import (  # noqa: E402
    GcWatch,
    bench_config,
    default_loop_name,
    loop_names,
    run_client,
    run_on,
)
from server.app import App  # noqa: E402
from server.runtime.clock import RealClock  # noqa: E402
from server.runtime.events import Event, MachineState  # noqa: E402
from server.transports.tcp import TcpTransport  # noqa: E402

RASTER_FILE = "laser-raster-tree.nc"
TARGET_RATIO = 0.6  # check-mode streaming against the bare server (issue 41)

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


@dataclass(slots=True)
class CheckRuns:
    """motiond in check mode on one event loop: the runs, and the same server idle."""

    loop: str
    runs: list[dict[str, Any]]  # the client's figures, plus stall_s and cpu_stall_s
    idle_stall_s: float

    @property
    def best(self) -> dict[str, Any]:
        return fastest(self.runs)


async def motiond_runs(path: Path, loop: str, repeat: int) -> CheckRuns:
    """Stream ``path`` to motiond in check mode ``repeat`` times: each run with its worst
    event-loop stall from ``$C`` on, and the worst stall of the same server idle for 1 s
    before."""
    app = App(bench_config(), clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    await asyncio.sleep(0.2)
    monitor = app.kernel.loop_monitor
    monitor.reset()
    await asyncio.sleep(1.0)
    idle_stall_s = monitor.worst_stall_s
    # measure from `$C` on to the `$C` that ends the stream: starting the client process (fork
    # and exec) and reading its figures after it exits are the benchmark's work, not the server's
    window: list[float] = []

    def on_state(state: MachineState) -> None:
        if state is MachineState.CHECK:
            monitor.reset()
        elif not window:
            window.extend((monitor.worst_stall_s, monitor.worst_cpu_stall_s))

    app.kernel.events.subscribe(Event.STATE, on_state)
    runs = []
    for _ in range(repeat):
        window.clear()
        with GcWatch() as gc_watch:
            gc_watch.switch(True)
            run = await run_client(app.transports[0].port, path,  # type: ignore[attr-defined]
                                   banner=True, check=True)
        stall_s, cpu_stall_s = window
        runs.append({**run, "stall_s": stall_s, "cpu_stall_s": cpu_stall_s,
                     "gc": gc_watch.collections, "gc_longest_s": gc_watch.longest_s})
    app.request_stop()
    await task
    return CheckRuns(loop, runs, idle_stall_s)


def throughput(result: BenchResult, loops: list[str], repeat: int) -> None:
    path = CORPUS / RASTER_FILE
    bare_lines = run_on("asyncio", lambda: bare_run(path, True, repeat))
    bare_chunks = run_on("asyncio", lambda: bare_run(path, False, repeat))
    checks = [run_on(loop, lambda loop=loop: motiond_runs(path, loop, repeat)) for loop in loops]
    bare_rate = bare_lines["lines"] / bare_lines["elapsed_s"]
    print(f"\n1. {RASTER_FILE}: {bare_lines['lines']:,} lines, character counting, "
          f"{WINDOW}-byte window")
    print(f"   {'server':36} {'seconds':>8} {'lines/s':>9} {'errors':>7} {'/bare per line':>14}")
    rows = [("bare asyncio server, ok per line", bare_lines),
            ("bare asyncio server, ok per chunk", bare_chunks)]
    rows += [(f"motiond, check mode ($C), {check.loop}", check.best) for check in checks]
    for label, run in rows:
        rate = run["lines"] / run["elapsed_s"]
        print(f"   {label:36} {run['elapsed_s']:8.2f} {rate:9,.0f} {run['errors']:7} "
              f"{rate / bare_rate:13.2f}x")
        result.add("throughput", label, lines=(run["lines"], "lines"),
                   elapsed=(run["elapsed_s"], "s"), rate=(rate, "lines/s"),
                   errors=(run["errors"], "lines"), ratio_to_bare_per_line=(rate / bare_rate, "x"))
    for check in checks:
        summarise_check(result, check, bare_rate, repeat)
    print(f"   (best of {repeat} runs each; the client runs in its own process)")


def summarise_check(result: BenchResult, check: CheckRuns, bare_rate: float, repeat: int) -> None:
    best = check.best
    ratio = best["lines"] / best["elapsed_s"] / bare_rate
    stall_s = max(run["stall_s"] for run in check.runs)
    cpu_stall_s = max(run["cpu_stall_s"] for run in check.runs)
    print(f"   {check.loop}: ratio to bare (ok per line) {ratio:.2f}x "
          f"(target >= {TARGET_RATIO:.2f}x) "
          f"{'OK' if ratio >= TARGET_RATIO else 'BELOW TARGET'}; worst stall while streaming "
          + " / ".join(f"{run['stall_s'] * 1000:.2f}" for run in check.runs)
          + " ms, own work " + " / ".join(f"{run['cpu_stall_s'] * 1000:.2f}" for run in check.runs)
          + f" ms (goal < 2 ms); idle for 1 s before: {check.idle_stall_s * 1000:.2f} ms; "
          + "collections (gen 0/1/2, longest ms) " + " / ".join(
              "{}/{}/{}, {:.2f}".format(*run["gc"], run["gc_longest_s"] * 1000)
              for run in check.runs))
    result.add("throughput", f"summary {check.loop}", ratio_to_bare_per_line=(ratio, "x"),
               stall_streaming=(stall_s * 1000, "ms"),
               cpu_stall_streaming=(cpu_stall_s * 1000, "ms"),
               stall_idle=(check.idle_stall_s * 1000, "ms"), repeat=(repeat, "runs"))


def run(quick: bool) -> BenchResult:
    result = BenchResult("streaming", quick)
    started = time.perf_counter()
    loops = loop_names()
    throughput(result, loops, repeat=2 if quick else 3)
    with tempfile.TemporaryDirectory() as workdir:
        steady_rate(result, loops, quick, Path(workdir), repeat=2 if quick else 3)
        fastest_sustained(result, default_loop_name(), quick, Path(workdir),
                          repeat=1 if quick else 2)
    print(f"\n(total {time.perf_counter() - started:.0f} s)")
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
