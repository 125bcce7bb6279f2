"""A motiond server and a latency probe, each in a process of its own (real sockets)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import socket
import sys
from collections.abc import AsyncIterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
AXES_TOML = "".join(
    f"[axes.{axis}]\nsteps_per_mm = 80\nmax_rate_mm_s = 500\naccel_mm_s2 = 3000\nmax_mm = 300\n"
    for axis in "xy"
)


_EPHEMERAL = Path("/proc/sys/net/ipv4/ip_local_port_range")
_HANDED_OUT: set[int] = set()


def free_port() -> int:
    """A port free on loopback now, for a server about to be started. It is chosen below
    Linux's ephemeral range, so no outgoing connection (five machines dialling the broker)
    takes it before the server binds it, and never twice in one process."""
    low = int(_EPHEMERAL.read_text().split()[0]) if _EPHEMERAL.exists() else 32768
    chooser = random.Random()
    while True:
        port = chooser.randrange(max(1024, low - 12000), low)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        _HANDED_OUT.add(port)
        return port


@dataclass
class Served:
    """A running ``motiond`` process and where it listens."""

    process: asyncio.subprocess.Process
    tcp_port: int
    http_port: int
    data_dir: Path
    log: list[str] = field(default_factory=list)
    jobs: Path | None = None  # [jobs] jobs_dir, when the config names one

    @property
    def jobs_dir(self) -> Path:
        return self.jobs if self.jobs is not None else self.data_dir / "jobs"

    @property
    def http(self) -> str:
        return f"127.0.0.1:{self.http_port}"


async def _wait_listening(port: int, process: asyncio.subprocess.Process) -> None:
    for _ in range(200):
        if process.returncode is not None:
            raise RuntimeError(f"motiond exited with {process.returncode}")
        with contextlib.suppress(OSError):
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            return
        await asyncio.sleep(0.05)
    raise TimeoutError(f"motiond did not listen on {port}")


@contextlib.asynccontextmanager
async def motiond(tmp_path: Path, extra_toml: str = "", *, args: Sequence[str] = (),
                  axes_toml: str = AXES_TOML, name: str = "machine",
                  home: Path | None = None,
                  env: Mapping[str, str] | None = None) -> AsyncIterator[Served]:
    """``motiond --config`` on free ports with ``extra_toml`` appended to a small XY machine
    (``axes_toml``), more command-line ``args`` (``--pty PATH``) and ``env``; ``name`` names
    its files. With ``home``, it runs as a user whose home that is, with the folders of its
    config (``extra_toml`` then holds the ``[jobs]`` section, a ``~`` is that home)."""
    environment = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    if home is None:
        data_dir = tmp_path / f"data-{name}" if name != "machine" else tmp_path / "data"
        (data_dir / "jobs").mkdir(parents=True, exist_ok=True)
        extra_toml = f"[jobs]\ndata_dir = '{data_dir}'\n" + extra_toml
    else:
        environment = {key: value for key, value in environment.items()
                       if not key.startswith("XDG_")}
        environment["HOME"] = str(home)
        data_dir = home / ".local" / "share" / "motiond"  # platformdirs' user data folder
    config = tmp_path / f"{name}.toml"
    config.write_text(axes_toml + extra_toml)
    log_path = tmp_path / f"{name}.log"  # its warnings, for a failing test
    for attempt in range(3):
        tcp_port, http_port = free_port(), free_port()
        logged = log_path.stat().st_size if log_path.exists() else 0
        with log_path.open("ab") as log_file:
            process = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "server.cli", "--config", str(config),
                "--host", "127.0.0.1", "--tcp-port", str(tcp_port),
                "--http-port", str(http_port), "--log-level", "warning", *args,
                cwd=REPO, env=environment, stdout=asyncio.subprocess.DEVNULL, stderr=log_file,
            )
        try:
            await _wait_listening(tcp_port, process)
            await _wait_listening(http_port, process)
            break
        except RuntimeError as exc:
            said = log_path.read_bytes()[logged:].decode(errors="replace")
            # A free port is free only until another program's connection takes it (five
            # machines dialling the broker at once): take two others.
            if "address already in use" in said and attempt < 2:
                continue
            raise RuntimeError(f"{exc}: {said[-2000:]}") from None
        except BaseException:
            await stop_process(process)
            raise
    try:
        yield Served(process, tcp_port, http_port, data_dir)
    finally:
        await stop_process(process)


async def stop_process(process: asyncio.subprocess.Process) -> None:
    """SIGTERM, then SIGKILL after 10 s: a child of a test never outlives it."""
    if process.returncode is None:
        process.terminate()
        try:
            await asyncio.wait_for(process.wait(), 10)
        except TimeoutError:
            process.kill()
            await process.wait()


@contextlib.asynccontextmanager
async def latency_probe(
    port: int, period_ms: float = 10.0, token: str | None = None
) -> AsyncIterator[dict[str, float]]:
    """Poll ``?`` from another process while the block runs; the dict holds its summary
    (``count``, ``p50_ms``, ``p99_ms``, ``max_ms``, ``missed``) once the block has ended."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "tests.support.latency_probe", "127.0.0.1", str(port),
        "--period-ms", str(period_ms), *(["--token", token] if token else []), cwd=REPO,
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
    )
    result: dict[str, float] = {}
    try:
        assert process.stdout is not None  # polling before the attack starts (however slow
        await asyncio.wait_for(process.stdout.readline(), 30)  # a loaded machine starts it)
        yield result
    finally:
        assert process.stdin is not None
        process.stdin.close()
        out, _ = await asyncio.wait_for(process.communicate(), 30)
        result.update(json.loads(out.decode().strip().splitlines()[-1]))
