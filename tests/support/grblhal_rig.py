"""Real grblHAL for the tests: the grblhal-sim rig in ``../shared/rigs/grblhal-sim``.

As :mod:`tests.support.grbl_rig` for Grbl 1.1h: :func:`rig_executable` builds it once into the
repository's ignored ``build/`` folder, :func:`grblhal_on_pty` runs a fresh board (its settings
in a temporary folder) on a pseudo-terminal, :func:`grblhal_direct` one on pipes with a
:class:`~tests.support.grbl_rig.GrblClient` past its banner. grblHAL reads input from a second
after it starts; its banner is ``GrblHAL 1.1f ['$' or '$HELP' for help]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import tty
from collections.abc import AsyncIterator
from pathlib import Path

from tests.support.grbl_rig import GrblClient
from tests.support.rigs import REPO, RIGS, rig

RIG = RIGS / "grblhal-sim"
BUILD = REPO / "build" / "grblhal-sim"
# As the Grbl rig's tests: fast axes, so the cases' moves take milliseconds.
FAST_SETTINGS = ("$110=20000", "$111=20000", "$112=20000", "$120=2000", "$121=2000",
                 "$122=2000")


def rig_executable() -> Path:
    """The built simulator; skips the test only when the rigs folder is absent."""
    rig("grblhal-sim")
    done = subprocess.run([str(RIG / "build"), str(BUILD)], capture_output=True, text=True,
                          timeout=900, check=True)
    return Path(done.stdout.strip().splitlines()[-1])


def _command(exe: Path) -> list[str]:
    return [str(exe), "-n", "-e", "EEPROM.DAT", "-b", "/dev/null", "-s", "/dev/null"]


@contextlib.asynccontextmanager
async def grblhal_on_pty(tmp_path: Path, name: str = "grblhal") -> AsyncIterator[str]:
    """A fresh grblHAL board on a pseudo-terminal; yields the device path to open."""
    exe = rig_executable()
    folder = tmp_path / f"{name}-settings"
    folder.mkdir()
    board, device = os.openpty()
    tty.setraw(device)
    tty.setraw(board)
    process = await asyncio.create_subprocess_exec(
        *_command(exe), stdin=board, stdout=board, stderr=subprocess.DEVNULL, cwd=folder)
    os.close(board)
    try:
        await asyncio.sleep(1.2)  # grblHAL reads input from a second after it starts
        yield os.ttyname(device)
    finally:
        await _stop(process)
        os.close(device)


@contextlib.asynccontextmanager
async def grblhal_direct(tmp_path: Path, name: str = "direct") -> AsyncIterator[GrblClient]:
    """A fresh grblHAL board on pipes, already past its banner and its first second."""
    exe = rig_executable()
    folder = tmp_path / f"{name}-settings"
    folder.mkdir()
    process = await asyncio.create_subprocess_exec(
        *_command(exe), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL, cwd=folder)
    assert process.stdin is not None and process.stdout is not None
    client = GrblClient(process.stdout, process.stdin)
    try:
        await client.banner()
        await asyncio.sleep(1.0)  # grblHAL reads input from a second after it starts
        yield client
    finally:
        await _stop(process)


async def _stop(process: asyncio.subprocess.Process) -> None:
    if process.returncode is None:
        process.kill()
    await process.wait()
