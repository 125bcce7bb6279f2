"""Real Grbl 1.1h for the tests: the grbl-sim rig in ``../shared/rigs/grbl-sim``.

:func:`rig_executable` builds it once into the repository's ignored ``build/`` folder (never
the user's home) and returns the simulator; :func:`grbl_on_pty` runs a fresh board (its EEPROM
in a temporary folder) on a pseudo-terminal and yields the path motiond opens;
:class:`GrblClient` talks to a Grbl-speaking stream line by line (send-response, ``?`` polls),
the board directly or motiond's front.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import subprocess
import tty
from collections.abc import AsyncIterator, Sequence
from pathlib import Path

from tests.support.rigs import REPO, RIGS, rig

RIG = RIGS / "grbl-sim"
BUILD = REPO / "build" / "grbl-sim"
# Fast axes, so the edge cases' moves take milliseconds (Grbl's defaults: 500 mm/min, 10 mm/s²).
# The rig's known residue (its README): very rarely a reply comes garbled (``0rror:20``, ``k``).
# An answer one character off is taken as the answer and counted in ``GrblClient.garbled``.
_GARBLED_ANSWER = re.compile(r"^(?:.?k|o.?|.rror:\d+|e.ror:\d+|er.or:\d+|err.r:\d+|"
                             r"erro.:\d+|error.\d+|rror:\d+|eror:\d+|erro:\d+)$")
# A parser state report is a list of words (G54, T0, F0, S0...): one a letter short or with a
# letter for a digit (``FG``) is the same residue, and taken as garbled, not compared.
_GC_REPORT = re.compile(r"\[GC:(?:[A-Z]-?\d+(?:\.\d+)?)(?: [A-Z]-?\d+(?:\.\d+)?)*\]")
FAST_SETTINGS = ("$110=20000", "$111=20000", "$112=20000", "$120=2000", "$121=2000",
                 "$122=2000")


def rig_executable() -> Path:
    """The built simulator; skips the test only when the rigs folder is absent."""
    rig("grbl-sim")
    done = subprocess.run([str(RIG / "build"), str(BUILD)], capture_output=True, text=True,
                          timeout=600, check=True)
    return Path(done.stdout.strip().splitlines()[-1])


def _command(exe: Path) -> list[str]:
    return ["stdbuf", "-o0", str(exe), "-n", "-b", "/dev/null", "-s", "/dev/null"]


@contextlib.asynccontextmanager
async def board_on_pty(command: Sequence[str], folder: Path, settle_s: float = 0.0
                       ) -> AsyncIterator[str]:
    """A fresh simulated board (``command``, run in ``folder``: its settings) on a
    pseudo-terminal, given ``settle_s`` before its first input; yields the device to open."""
    folder.mkdir()
    board, device = os.openpty()
    tty.setraw(device)
    process = await asyncio.create_subprocess_exec(
        *command, stdin=board, stdout=board, stderr=subprocess.DEVNULL, cwd=folder)
    os.close(board)
    try:
        await asyncio.sleep(settle_s)
        yield os.ttyname(device)
    finally:
        await _stop(process)
        os.close(device)


@contextlib.asynccontextmanager
async def board_direct(command: Sequence[str], folder: Path, settle_s: float = 0.0
                       ) -> AsyncIterator[GrblClient]:
    """A fresh simulated board on pipes, already past its banner and ``settle_s``."""
    folder.mkdir()
    process = await asyncio.create_subprocess_exec(
        *command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL, cwd=folder)
    assert process.stdin is not None and process.stdout is not None
    client = GrblClient(process.stdout, process.stdin)
    try:
        await client.banner()
        await asyncio.sleep(settle_s)
        yield client
    finally:
        await _stop(process)


def grbl_on_pty(tmp_path: Path, name: str = "grbl") -> contextlib.AbstractAsyncContextManager[str]:
    """A fresh Grbl board (its EEPROM in a temporary folder) on a pseudo-terminal."""
    return board_on_pty(_command(rig_executable()), tmp_path / f"{name}-eeprom")


def grbl_direct(tmp_path: Path, name: str = "direct"
                ) -> contextlib.AbstractAsyncContextManager[GrblClient]:
    """A fresh Grbl board on pipes, already past its banner."""
    return board_direct(_command(rig_executable()), tmp_path / f"{name}-eeprom")


async def _stop(process: asyncio.subprocess.Process) -> None:
    if process.returncode is None:
        process.kill()
    await process.wait()


class GrblClient:
    """Send-response over a Grbl stream: a line's messages and its ``ok`` / ``error:N``."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.pushed: list[str] = []  # lines that were neither a reply nor a report
        self.garbled = 0  # answers taken although garbled (the rig's residue)

    @classmethod
    async def connect(cls, port: int) -> GrblClient:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        client = cls(reader, writer)
        await client.banner()
        return client

    async def line(self, timeout_s: float = 30.0) -> str:
        while True:
            data = await asyncio.wait_for(self.reader.readline(), timeout_s)
            if not data:
                raise ConnectionError("the stream closed")
            text = data.decode("ascii", "replace").strip()
            if text:
                return text

    async def banner(self) -> str:
        while not (text := await self.line()).startswith(("Grbl ", "GrblHAL ")):
            pass
        return text

    async def send(self, text: str, timeout_s: float = 30.0) -> list[str]:
        """One line; returns what came back up to and including its reply."""
        self.writer.write(text.encode() + b"\n")
        out = []
        while True:
            line = await self.line(timeout_s)
            if line.startswith("<"):
                continue
            if line.startswith("[GC:") and not _GC_REPORT.fullmatch(line):
                self.garbled += 1
                line = "garbled:" + line
            out.append(line)
            if line == "ok" or re.fullmatch(r"error:\d+", line):
                return out
            if _GARBLED_ANSWER.match(line):
                self.garbled += 1
                out[-1] = "garbled:" + line
                return out

    async def report(self, attempts: int = 30) -> str:
        """A status report; asked again after a second without one (a garbled report)."""
        for _ in range(attempts):
            self.writer.write(b"?")
            try:
                while not (line := await self.line(1.0)).startswith("<"):
                    self.pushed.append(line)
            except TimeoutError:
                continue
            return line
        raise TimeoutError("no status report")

    async def settle(self, timeout_s: float = 30.0) -> str:
        """Poll until two reports in a row say Idle or Alarm; the last report.

        One is not enough: Grbl starts the cycle of a line it has answered only when its
        serial buffer runs dry, and the same pass reports first, so a ``?`` sent just after
        ``ok`` can say Idle with the block still queued (``Bf:14``)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        at_rest = 0
        while True:
            report = await self.report()
            at_rest = at_rest + 1 if report.startswith(("<Idle", "<Alarm")) else 0
            if at_rest == 2 or loop.time() > deadline:
                return report
            if not at_rest:
                await asyncio.sleep(0.02)

    async def each(self, lines: Sequence[str]) -> list[tuple[str, ...]]:
        """Every line sent alone, waiting for the machine to settle after it."""
        replies = []
        for text in lines:
            replies.append(tuple(await self.send(text)))
            await self.settle()
        return replies

    def close(self) -> None:
        self.writer.close()
