"""A laser machine for the stop tests (tests/e2e/test_one_stop*.py), served in this process on
real ports, and the clients that speak to it: a Grbl line-protocol client over TCP, the JSON
API over a real WebSocket (:mod:`tests.support.api_client`) and Klipper's API over its real
Unix socket (JSON objects each ended by 0x03, as Moonraker sends them).

What the machine did is read from the simulated backend, the ground truth under every
report: the steps it received (``steps_travelled``, per axis ``steps``) and every change of
the laser's PWM output (``output_trace``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.api.server import http_with_api
from server.app import App
from server.backends.sim import SimBackend
from server.paths import jobs_dir
from server.runtime.clock import RealClock
from server.transports.tcp import TcpTransport
from server.transports.websocket import HttpTransport
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.klippy_client import KlippyClient
from tests.support.senders import wait_for

BANNER = "Grbl 1.1h ['$' for help]"
# A job whose fit check takes about 2 s here, so that a stop 0.4 s after its start lands during
# the check: 100,000 relative moves (G91: read one line at a time, as the plan's batch path
# takes only absolute runs; 1.4 MB of absolute moves is checked in a fraction of a second).
CHECK_LINES = 100_000
STOP_AFTER_S = 0.4


def slow_to_check_job() -> str:
    return "G21 G91\nM3 S1000\n" + "G1 X0.5 Y0.5 F600\nG1 X-0.5 Y-0.5\n" * (CHECK_LINES // 2)

LASER_PIN = "laser"


class LineClient:
    """A sender on the TCP line protocol; every line it receives is kept, in order."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.lines: list[str] = []
        self.ended = False
        self._changed = asyncio.Event()
        self._task = asyncio.create_task(self._collect(reader))

    @classmethod
    async def open(cls, port: int) -> LineClient:
        """Connect and wait for the banner."""
        client = cls(*await asyncio.open_connection("127.0.0.1", port))
        await client.until(lambda got: BANNER in got)
        return client

    async def _collect(self, reader: asyncio.StreamReader) -> None:
        buffer = b""
        try:
            while chunk := await reader.read(65536):
                buffer += chunk
                *complete, buffer = buffer.split(b"\n")
                self.lines += [line.decode("utf-8", "replace").strip("\r") for line in complete]
                self._changed.set()
        except OSError:
            pass
        finally:
            self.ended = True
            self._changed.set()

    def send(self, data: bytes) -> None:
        """Write ``data`` as it is, in one write."""
        self.writer.write(data)

    async def until(self, done: Callable[[list[str]], bool], timeout_s: float = 5.0) -> list[str]:
        """Wait until ``done(lines)`` holds; the lines so far (AssertionError after
        ``timeout_s``, with the last lines)."""
        try:
            async with asyncio.timeout(timeout_s):
                while not done(self.lines):
                    if self.ended:
                        raise AssertionError(f"connection ended; last lines {self.lines[-8:]}")
                    self._changed.clear()
                    await self._changed.wait()
        except TimeoutError:
            raise AssertionError(
                f"not within {timeout_s} s; last lines {self.lines[-8:]}") from None
        return self.lines

    async def report(self) -> str:
        """A fresh status report (``?``)."""
        mark = len(self.lines)
        self.send(b"?")
        await self.until(lambda got: any(line.startswith("<") for line in got[mark:]))
        return next(line for line in self.lines[mark:] if line.startswith("<"))

    async def command(self, line: str, timeout_s: float = 5.0) -> list[str]:
        """Send one line; what came back up to and with its reply (``ok`` or ``error:N``)."""
        mark = len(self.lines)
        self.send(line.encode() + b"\n")
        await self.until(lambda got: any(is_reply(text) for text in got[mark:]), timeout_s)
        answer = self.lines[mark:]
        end = next(index for index, text in enumerate(answer) if is_reply(text))
        return answer[: end + 1]

    async def wait_state(self, prefix: str, timeout_s: float = 5.0) -> str:
        """Poll ``?`` until the state starts with ``prefix`` (``Hold:0``, ``Idle``); that report."""
        deadline = time.monotonic() + timeout_s
        while True:
            report = await self.report()
            if report[1:].startswith(prefix):
                return report
            if time.monotonic() > deadline:
                raise AssertionError(f"no {prefix} within {timeout_s} s: {report}")
            await asyncio.sleep(0.02)

    def replies(self, start: int = 0) -> list[str]:
        return [line for line in self.lines[start:] if is_reply(line)]

    def close(self) -> None:
        self._task.cancel()
        self.writer.transport.abort()


def is_reply(line: str) -> bool:
    return line == "ok" or line.startswith("error:")


def field_of(report: str, name: str) -> str | None:
    """One field of a status report (``FS``, ``WCO``, ``A``), None when it is absent."""
    for part in report.strip("<>").split("|"):
        if part.startswith(f"{name}:"):
            return part[len(name) + 1 :]
    return None


@dataclass
class Rig:
    """The served machine: its app (in this process), ports and Klipper API socket."""

    app: App
    socket: Path | None
    clients: list[LineClient] = field(default_factory=list)

    @property
    def tcp_port(self) -> int:
        return next(t.port for t in self.app.transports if isinstance(t, TcpTransport))

    @property
    def http(self) -> str:
        port = next(t.port for t in self.app.transports if isinstance(t, HttpTransport))
        return f"127.0.0.1:{port}"

    @property
    def backend(self) -> SimBackend:
        backend = self.app.kernel.machine.backend
        assert isinstance(backend, SimBackend)
        return backend

    async def tcp(self) -> LineClient:
        """A new TCP connection, past its banner (closed with the rig)."""
        client = await LineClient.open(self.tcp_port)
        self.clients.append(client)
        return client

    @contextlib.asynccontextmanager
    async def klippy(self) -> AsyncIterator[KlippyClient]:
        assert self.socket is not None, "a rig with klippy=True"
        reader, writer = await asyncio.open_unix_connection(str(self.socket))
        client = KlippyClient(reader, writer)
        try:
            yield client
        finally:
            client.close()

    def write_job(self, name: str, text: str) -> None:
        folder = jobs_dir(self.app.kernel.config.core)
        folder.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text)

    # -- what the machine did --------------------------------------------------------------
    def laser_mark(self) -> int:
        """A place in the laser's output trace: :meth:`laser_fired_since` looks after it."""
        return len(self.backend.output_trace)

    def laser_fired_since(self, mark: int) -> list[float]:
        """Every non-zero duty the laser's output was set to after ``mark``."""
        return [value for _, name, value in self.backend.output_trace[mark:]
                if name == LASER_PIN and value > 0.0]

    def laser_duty(self) -> float:
        return self.backend.output(LASER_PIN)

    async def moving(self, timeout_s: float = 5.0) -> None:
        """Wait until the steps flow (the machine is moving)."""
        start = self.backend.steps_travelled
        deadline = time.monotonic() + timeout_s
        while self.backend.steps_travelled - start < 40:  # half a millimetre at 80 steps/mm
            assert time.monotonic() < deadline, "the machine never moved"
            await asyncio.sleep(0.01)

    async def assert_still(self, seconds: float, what: str) -> None:
        """Nothing moves and the laser stays off for ``seconds`` (watched every 20 ms)."""
        steps, mark = list(self.backend.steps), self.laser_mark()
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            await asyncio.sleep(0.02)
            assert self.backend.steps == steps, f"{what}: the machine moved"
            assert self.laser_duty() == 0.0, f"{what}: the laser is on"
        assert not self.laser_fired_since(mark), f"{what}: the laser fired"


@contextlib.asynccontextmanager
async def stop_rig(tmp_path: Path, *, klippy: bool = False, **sections: Any) -> AsyncIterator[Rig]:
    """A small XYZ laser machine (``[laser]``, soft limits on, laser mode) with TCP, HTTP
    with the JSON API and, with ``klippy``, Klipper's API socket; ``sections`` are merged
    into its config. The real clock."""
    socket = tmp_path / "klippy.sock" if klippy else None
    extra: dict[str, Any] = {"laser": {"pin": LASER_PIN}, **sections}
    extra["jobs"] = {"data_dir": str(tmp_path / "data"), **sections.get("jobs", {})}
    if socket is not None:
        extra["klippy_api"] = {"socket": str(socket)}
    config = make_config(extra)
    async with running(config, RealClock(), transports=[TcpTransport, http_with_api]) as app:
        rig = Rig(app, socket)
        if socket is not None:
            await wait_for(socket.exists, 5.0, "Klipper's API socket")
        try:
            yield rig
        finally:
            for client in rig.clients:
                client.close()


OFFSET = "[G54:5.000,3.000,0.000]"  # G10 L20 P1 X-5 Y-3 at the origin


async def assert_a_reset_boards_modes(rig: Rig, sender: LineClient) -> None:
    """After a stop and its unlock: ``$G`` shows ``M5``, ``S0`` and ``M9``, the work offset
    (:data:`OFFSET`) stays, and a plain ``G1`` moves with the laser off."""
    modal = (await sender.command("$G"))[0].strip("[]").split()
    assert {"M5", "S0", "M9"} <= set(modal), modal
    assert OFFSET in await sender.command("$#"), "the work offset stays"
    mark = rig.laser_mark()
    assert await sender.command("G1 X10 F600") == ["ok"]
    await rig.moving()
    await sender.wait_state("Idle")
    where = field_of(await sender.report(), "MPos")
    assert where == "15.000,0.000,0.000", "it moved, to work X10"
    assert not rig.laser_fired_since(mark), "the laser stayed off"
