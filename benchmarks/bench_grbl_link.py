"""Streaming through motiond to a Grbl controller, against streaming to the controller directly.

The controller is a second motiond (its simulated machine) on a pseudo-terminal, in check mode
(``$C``: every line parsed and interpreted, nothing moves, so motion time does not hide the
protocol's cost). The same raster lines (laser-raster-tree.nc) are streamed with character
counting, side by side in one run:

1. directly to the controller over its pseudo-terminal (127-byte window, as the link counts);
2. directly to the controller over TCP (the streaming benchmark's client, 128-byte window);
3. through motiond with ``[backend] kind = "grbl"`` on that pseudo-terminal: the client streams
   to motiond over TCP, motiond interprets each line, then streams it to the controller.

Prints lines/s for each and the ratio of the chain to each direct run (the overhead motiond
adds). Run: ``python -m benchmarks grbl [--quick] [--json]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import tempfile
import time
import tty
from collections import deque
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

if not __package__:  # run as a script: find the repo
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import CORPUS, BenchResult, standalone  # noqa: E402
from benchmarks.stream_client import HOST  # noqa: E402
from benchmarks.streaming_support import run_client  # noqa: E402
from server.app import App  # noqa: E402
from server.backends.grbl.machine import GrblMachine  # noqa: E402
from server.config_loader import build_config  # noqa: E402
from server.runtime.clock import RealClock  # noqa: E402
from server.transports.tcp import TcpTransport  # noqa: E402
from tests.support.processes import free_port  # noqa: E402

RASTER_FILE = "laser-raster-tree.nc"
REPO = Path(__file__).resolve().parent.parent
AXES = {"max_rate_mm_s": 10000.0, "accel_mm_s2": 50000.0, "min_mm": -100000.0,
        "max_mm": 100000.0, "steps_per_mm": 80.0}
PTY_WINDOW = 127


def controller_toml(data_dir: Path) -> str:
    axes = "".join(f"[axes.{name}]\n" + "".join(f"{key} = {value}\n" for key, value in
                                                AXES.items()) for name in "xyz")
    return (f"[machine]\nsoft_limits = false\n{axes}[jobs]\ndata_dir = '{data_dir}'\n"
            "[http]\nenabled = false\n")


@contextlib.asynccontextmanager
async def controller(workdir: Path) -> AsyncIterator[tuple[Path, int]]:
    """A motiond subprocess on a pseudo-terminal: its path and TCP port."""
    config, pty = workdir / "controller.toml", workdir / "ttyController"
    config.write_text(controller_toml(workdir / "data"))
    port = free_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.cli", "--config", str(config), "--host", HOST,
        "--tcp-port", str(port), "--pty", str(pty), "--log-level", "warning", cwd=REPO,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
    try:
        for _ in range(200):
            with contextlib.suppress(OSError):
                _, writer = await asyncio.open_connection(HOST, port)
                writer.close()
                break
            await asyncio.sleep(0.05)
        yield pty, port
    finally:
        process.terminate()
        await process.wait()


async def check_mode(port: int, on: bool) -> None:
    """Put the controller in check mode (``$C``) or out of it, whatever it was in (motiond
    stopping resets the board with Ctrl-X, which leaves check mode)."""
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(b"?")
    while not (line := (await reader.readline()).strip()).startswith(b"<"):
        pass
    if line.startswith(b"<Check") != on:
        writer.write(b"$C\n")
        while not (await reader.readline()).strip().startswith((b"ok", b"error")):
            pass
    writer.close()


def stream_pty(path: Path, lines: list[str]) -> dict[str, Any]:
    """Character counting over the pseudo-terminal, blocking (run in a thread)."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    data = [line.encode() + b"\n" for line in lines]
    pending, unacked = b"", deque[int]()
    used = answered = errors = index = 0
    while b"Grbl " not in pending:
        pending += os.read(fd, 4096)
    pending = b""
    started = time.perf_counter()
    while answered < len(data):
        batch = []
        while index < len(data) and used + len(data[index]) <= PTY_WINDOW:
            batch.append(data[index])
            unacked.append(len(data[index]))
            used += len(data[index])
            index += 1
        if batch:
            os.write(fd, b"".join(batch))
        pending += os.read(fd, 65536)
        *complete, pending = pending.split(b"\n")
        for line in complete:
            line = line.strip()
            if line == b"ok" or line.startswith(b"error"):
                errors += line.startswith(b"error")
                answered += 1
                used -= unacked.popleft()
    elapsed_s = time.perf_counter() - started
    os.close(fd)
    return {"lines": len(data), "elapsed_s": elapsed_s, "errors": errors}


async def through_motiond(workdir: Path, pty: Path, path: Path) -> dict[str, Any]:
    """Stream ``path`` to an in-process motiond whose backend is the controller on ``pty``."""
    axes = {name: AXES for name in "xyz"}
    config = build_config({
        "machine": {"soft_limits": False}, "axes": axes, "tcp": {"host": HOST, "port": 0},
        "jobs": {"data_dir": str(workdir / "link-data")},
        "backend": {"kind": "grbl", "serial": str(pty)}}, "bench_grbl_link")
    app = App(config, clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    machine = app.kernel.machine
    assert isinstance(machine, GrblMachine)
    for _ in range(500):  # the handshake: banner, $I, $$, $#, $G
        if machine.controller.ready:
            break
        await asyncio.sleep(0.02)
    result = await run_client(app.transports[0].port, path,  # type: ignore[attr-defined]
                              banner=True)
    app.request_stop()
    await task
    return result


async def measure(lines: list[str], repeat: int) -> dict[str, dict[str, Any]]:
    with tempfile.TemporaryDirectory() as name:
        workdir = Path(name)
        path = workdir / "job.nc"
        path.write_text("\n".join(lines) + "\n")
        runs: dict[str, list[dict[str, Any]]] = {"pty": [], "tcp": [], "motiond": []}
        async with controller(workdir) as (pty, port):
            for _ in range(repeat):  # side by side, in turn
                await check_mode(port, False)  # the client toggles it around its run
                runs["tcp"].append(await run_client(port, path, banner=True, check=True))
                await check_mode(port, True)
                runs["pty"].append(await asyncio.to_thread(stream_pty, pty, lines))
                await check_mode(port, True)
                runs["motiond"].append(await through_motiond(workdir, pty, path))
        return {key: min(values, key=lambda run: run["elapsed_s"]) for key, values in
                runs.items()}


def run(quick: bool) -> BenchResult:
    result = BenchResult("grbl", quick)
    lines = (CORPUS / RASTER_FILE).read_text().splitlines()[: 4000 if quick else 20000]
    best = asyncio.run(measure(lines, repeat=1 if quick else 3))
    rates = {key: run["lines"] / run["elapsed_s"] for key, run in best.items()}
    print(f"{RASTER_FILE}: {len(lines):,} lines, character counting, controller in check mode")
    print(f"   {'path':44} {'seconds':>8} {'lines/s':>9} {'errors':>7}")
    labels = {"pty": "direct to the controller, pty", "tcp": "direct to the controller, TCP",
              "motiond": "client -TCP-> motiond -pty-> controller"}
    for key, label in labels.items():
        run_ = best[key]
        print(f"   {label:44} {run_['elapsed_s']:8.2f} {rates[key]:9,.0f} {run_['errors']:7}")
        result.add("throughput", label, lines=(run_["lines"], "lines"),
                   elapsed=(run_["elapsed_s"], "s"), rate=(rates[key], "lines/s"),
                   errors=(run_["errors"], "lines"))
    to_pty, to_tcp = rates["motiond"] / rates["pty"], rates["motiond"] / rates["tcp"]
    print(f"   through motiond / direct over the pty: {to_pty:.2f}x; "
          f"/ direct over TCP: {to_tcp:.2f}x (best of {1 if quick else 3} runs each)")
    result.add("ratio", "through motiond / direct", to_pty=(to_pty, "x"), to_tcp=(to_tcp, "x"))
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, (__doc__ or "").splitlines()[0]))
