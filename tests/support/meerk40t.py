"""MeerK40t (PyPI, a Python laser program) as a real sender for the e2e suite and as the
reference CAM the drawing import is compared with (:func:`meerk40t_gcode`), in its own virtual
environment, without its GUI (``meerk40t -Z``).

The environment is built once into ``build/meerk40t-<version>/`` (ignored by git; ``.ci/run``
builds it before the tests with ``python3 -m tests.support.meerk40t``), with
``websocket-client`` (its WebSocket connection) and Pillow and numpy (which it imports at
start). :class:`MeerK40t` runs it with ``HOME`` and the XDG folders in a folder of the test's,
so its settings never touch the user's, and feeds console commands.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
VERSION = "0.9.9100"
VENV = REPO / "build" / f"meerk40t-{VERSION}"
EXECUTABLE = VENV / "bin" / "meerk40t"
PACKAGES = [f"meerk40t=={VERSION}", "websocket-client", "pillow", "numpy"]


def ensure_venv() -> Path:
    """The ``meerk40t`` executable, building its environment first if it is missing."""
    if not EXECUTABLE.exists():
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", *PACKAGES], check=True)
    return EXECUTABLE


class MeerK40t:
    """One ``meerk40t -Z -c`` process; its console output is kept in :attr:`output`."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process
        self.output = ""
        self._reader = asyncio.get_running_loop().create_task(self._read())

    async def _read(self) -> None:
        assert self.process.stdout is not None
        while chunk := await self.process.stdout.read(4096):
            self.output += chunk.decode("utf-8", "replace")

    async def command(self, *lines: str) -> None:
        """Console commands, as typed."""
        assert self.process.stdin is not None
        self.process.stdin.write("".join(f"{line}\n" for line in lines).encode())
        await self.process.stdin.drain()

    async def grbl_device_on(self, url_host: str, port: int, interface: str = "ws") -> None:
        """A generic Grbl device on ``interface`` (``ws``: ``ws://host:port/``), made active."""
        await self.command("device add grbl-generic", "device activate 1",
                           f"set -p grbl interface {interface}", f"set -p grbl address {url_host}",
                           f"set -p grbl port {port}", "signal update_interface")
        await asyncio.sleep(1.0)  # its signals are delivered by its scheduler, a tick later

    async def close(self) -> int:
        """``quit``, then its exit status (killed after 10 s)."""
        with contextlib.suppress(ConnectionError):
            await self.command("quit")
        try:
            await asyncio.wait_for(self.process.wait(), 10)
        except TimeoutError:
            self.process.kill()
            await self.process.wait()
        await self._reader
        return self.process.returncode or 0


@contextlib.asynccontextmanager
async def meerk40t(folder: Path) -> AsyncIterator[MeerK40t]:
    """MeerK40t with its settings in ``folder``, started and ready for console commands."""
    executable = ensure_venv()
    home = folder / "home"
    home.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HOME": str(home), "XDG_CONFIG_HOME": str(home / ".config"),
           "XDG_DATA_HOME": str(home / ".local" / "share"), "PYTHONUNBUFFERED": "1"}
    process = await asyncio.create_subprocess_exec(
        str(executable), "-Z", "-c", "-X", stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, env=env, cwd=folder)
    program = MeerK40t(process)
    try:
        await asyncio.sleep(3.0)  # its plugins load before the console reads
        yield program
    finally:
        await program.close()


def meerk40t_gcode(svg: Path, out: Path, home: Path) -> str:
    """MeerK40t's G-code for ``svg`` on its generic Grbl device, every element in one engrave
    (line) operation at its defaults, planned and optimised as its GUI would."""
    commands = ["service device start -i grbl 0", "operation* delete", "element* engrave",
                "plan copy preprocess validate blob preopt optimize", f"plan save_job {out}",
                "quit"]
    argv = [str(ensure_venv()), "-Z", "-X", "-A", str(svg)]
    for command in commands:
        argv += ["-e", command]
    home.mkdir(parents=True, exist_ok=True)
    subprocess.run(argv, env={**os.environ, "HOME": str(home)}, check=True,
                   capture_output=True, timeout=120)
    return out.read_text()


if __name__ == "__main__":
    print(ensure_venv())
