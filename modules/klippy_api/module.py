"""``[klippy_api]``: Klipper's API socket, so Moonraker and its front-ends drive motiond.

    [klippy_api]
    socket = "/run/motiond/klippy_uds"

motiond serves Klipper's "webhooks" API (JSON objects ended by ``\\x03``, see
:mod:`modules.klippy_api.wire`) on that Unix socket; Moonraker's ``klippy_uds_address`` points
at it, and Mainsail, Fluidd, KlipperScreen and Home Assistant's Moonraker integration then show
and drive this machine. The socket is created owner-only (mode 0600, set before it exists):
whoever can open it controls the machine, like a token holder.

Each connection is a :class:`~modules.klippy_api.session.Session`; the printer objects come
from :mod:`modules.klippy_api.objects`, built at most once per loop turn and shared by every
request and push of that turn. Subscribers get what changed ``status_hz`` times a second, and
at once when the machine's or the job's state changes. Messages the machine pushes to every
sender (alarms, ``[MSG:...]``) go to the G-code output subscribers.

The socket is bounded like every other input (:mod:`modules.klippy_api.connection`): at most
:data:`MAX_CONNECTIONS` clients (the next is told so and closed), requests and pushes within
one :class:`~modules.klippy_api.budget.LoopBudget` of loop time, waiting scripts within
:data:`SCRIPT_BYTES` together, answers within a bounded queue per client.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import platform
import socket
import stat
import sys
import time
from pathlib import Path
from typing import Any

from pydantic import Field

from modules.klippy_api import objects as printer
from modules.klippy_api.budget import ByteBudget, LoopBudget
from modules.klippy_api.connection import (
    READ_BYTES,
    Connection,
    refuse,
    serve,
)
from modules.klippy_api.gcode import HELP
from modules.klippy_api.scripts import response_text
from server import __version__
from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.paths import jobs_dir
from server.runtime.events import Event

MAX_CONNECTIONS = 8  # Moonraker takes one; a few direct tools beside it
SCRIPT_BYTES = 4 << 20  # all connections' waiting scripts together
PUSHES_WAITING = 8  # state changes whose snapshots wait for the push task
# Klipper's source folder as Moonraker reads it: its config/ and docs/ (README files that
# point at motiond's), so Moonraker's config_examples and docs roots are valid folders.
KLIPPER_PATH = Path(__file__).resolve().parent / "klipper"


class KlippyApiConfig(ModuleConfig):
    socket: Path = Field(description="the Unix socket Moonraker's klippy_uds_address names")
    status_hz: float = Field(4.0, gt=0, le=50, description="subscription pushes per second")


class KlippyApi(Module):
    """The Unix-socket server and what its sessions share (implements ``session.Hub``)."""

    name = "klippy_api"
    Config = KlippyApiConfig

    def __init__(self, ctx: ModuleContext, config: KlippyApiConfig) -> None:
        super().__init__(ctx, config)
        self.config: KlippyApiConfig = config
        self.path = config.socket.expanduser()
        core = ctx.core
        rates = [axis.max_rate_mm_s for name, axis in core.axes.items() if name.upper() in "XY"]
        self.jog_feed_mm_min = 60.0 * min(rates or [10.0])
        self.extra = printer.Extra()
        self.times = printer.JobTimes()
        self.job_state: str | None = None
        self.machine = printer.Machine((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 0.0,
                                       Path(), frozenset())
        self.connections: set[Connection] = set()
        self.budget = LoopBudget()
        self.script_bytes = ByteBudget(SCRIPT_BYTES)
        self._snapshot: dict[str, Any] | None = None
        self._pushes: collections.deque[dict[str, Any]] = collections.deque(
            maxlen=PUSHES_WAITING)
        self._push_now = asyncio.Event()
        self._refused, self._refusal_logged_s = 0, float("-inf")
        ctx.subscribe(Event.PUSH, lambda message: self.output(response_text(str(message))))
        ctx.subscribe(Event.JOB, self._on_job)
        for event in (Event.STATE, Event.HALT, Event.CLEAR_HALT):
            ctx.subscribe(event, lambda *_: self._changed())

    # -- Hub --------------------------------------------------------------------------------
    def objects(self) -> dict[str, Any]:
        """Every printer object now: built once per loop turn (a flood of queries reads one
        snapshot), forgotten at the next turn or when the state changes."""
        if self._snapshot is None:
            self.extra.host = _host_stats()
            self.extra.durations_s = self.times.durations(self.ctx.clock.now_s())
            self._snapshot = printer.build_objects(self.ctx.status(), self.machine, self.extra)
            asyncio.get_running_loop().call_soon(self._forget_snapshot)
        return self._snapshot

    def _forget_snapshot(self) -> None:
        self._snapshot = None

    def info(self) -> dict[str, Any]:
        hooks = printer.webhooks(self.ctx.status())
        return {
            "state": hooks["state"], "state_message": hooks["state_message"],
            "hostname": socket.gethostname(), "software_version": f"motiond {__version__}",
            "cpu_info": platform.processor() or platform.machine(), "app": "Klipper",
            "klipper_path": str(KLIPPER_PATH), "python_path": sys.executable,
            **_log_file(),
            "process_id": os.getpid(), "user_id": os.getuid(), "group_id": os.getgid(),
        }

    def set_message(self, text: str | None) -> None:
        self.extra.message = text

    def output(self, text: str) -> None:
        for connection in list(self.connections):
            connection.session.push_output(text)

    def restart(self) -> None:
        """After RESTART/FIRMWARE_RESTART: the last job is forgotten (``print_stats`` is
        ``standby``, as after Klipper's restart) and every connection closes."""
        job = self.ctx.status().get("job") or {}
        if job:
            self.extra.forgotten_job = (str(job["name"]), float(job["started_s"]))
        for connection in list(self.connections):
            connection.close()

    def status(self) -> dict[str, Any]:
        return {"socket": str(self.path), "clients": len(self.connections)}

    # -- running ----------------------------------------------------------------------------
    async def run(self) -> None:
        self.machine = self._describe()
        server = await asyncio.start_unix_server(
            self._serve, sock=_listening_socket(self.path), limit=READ_BYTES)
        try:
            async with server:
                await self._push_status()
        finally:
            self.restart()
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()

    def _describe(self) -> printer.Machine:
        core = self.ctx.core
        axes = {name.upper(): axis for name, axis in core.axes.items()}
        low = tuple(axes[a].min_mm if a in axes else 0.0 for a in "XYZ")
        high = tuple(axes[a].max_mm if a in axes else 0.0 for a in "XYZ")
        planar = [axes[a] for a in "XY" if a in axes] or list(axes.values())
        try:
            homing = self.ctx.lookup("endstops")
            homeable = frozenset(axis.name.lower() for axis in getattr(homing, "axes", []))
        except KeyError:
            homeable = frozenset()
        return printer.Machine(
            (low[0], low[1], low[2]), (high[0], high[1], high[2]),
            max(axis.max_rate_mm_s for axis in planar), max(axis.accel_mm_s2 for axis in planar),
            jobs_dir(core).resolve(), homeable, dict(HELP),
            "".join(axis.lower() for axis in "XYZ" if axis in axes))

    async def _push_status(self) -> None:
        """Push what changed to every subscriber ``status_hz`` times a second, and each
        snapshot taken at a state change (a pause and resume between two periods are two
        changes), one session at a time within the loop budget."""
        loop = asyncio.get_running_loop()
        period_s = 1.0 / self.config.status_hz
        next_s = loop.time() + period_s
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(next_s):
                    await self._push_now.wait()
            self._push_now.clear()
            while self._pushes:
                await self._push(self._pushes.popleft())
            if loop.time() >= next_s:
                next_s = max(next_s + period_s, loop.time())
                await self._push(None)

    async def _push(self, snapshot: dict[str, Any] | None) -> None:
        """One push to each subscriber: of ``snapshot``, or of the objects at its turn."""
        for connection in list(self.connections):
            session = connection.session
            if session.subscription and not connection.closed:
                await self.budget.turn()
                session.push_status(self.objects() if snapshot is None else snapshot)

    def _changed(self) -> None:
        """The machine's or the job's state changed: snapshot it now for the subscribers."""
        self._snapshot = None
        if any(connection.session.subscription for connection in self.connections):
            self._pushes.append(self.objects())
            self._push_now.set()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self.connections) >= MAX_CONNECTIONS:
            self._log_refusal()
            await refuse(reader, writer, f"too many API connections (at most "
                         f"{MAX_CONNECTIONS})")
            return
        connection = Connection(writer, self)
        self.connections.add(connection)
        try:
            await serve(connection, reader, self, self.ctx.log)
        finally:
            self.connections.discard(connection)

    def _log_refusal(self) -> None:
        """Log refused clients at most once a second (a flood of them writes one line)."""
        self._refused += 1
        now_s = time.monotonic()
        if now_s - self._refusal_logged_s >= 1.0:
            self.ctx.log.warning("%d API client(s) refused since the last such line: %d "
                                 "connections already", self._refused, MAX_CONNECTIONS)
            self._refusal_logged_s, self._refused = now_s, 0

    def _on_job(self, progress: Any) -> None:
        self.job_state = None if progress is None else str(progress.state)
        if progress is not None:
            self.times.update(progress.name, progress.started_s, progress.state,
                              self.ctx.clock.now_s())
        if progress is not None and progress.state == "running":
            try:
                self.extra.file_size_bytes = (self.machine.jobs_dir / progress.name).stat(
                ).st_size
            except OSError:
                self.extra.file_size_bytes = 0
        self._changed()


def _listening_socket(path: Path) -> socket.socket:
    """A Unix socket at ``path`` (its folder made if missing), owner-only from the moment it
    exists; a stale socket file is replaced, anything else at ``path`` (or a live server)
    refused."""
    with contextlib.suppress(FileNotFoundError):
        if not stat.S_ISSOCK(path.lstat().st_mode):
            raise RuntimeError(f"{path} exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        with probe:
            if probe.connect_ex(str(path)) == 0:
                raise RuntimeError(f"{path}: another server is listening there")
        path.unlink()
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)  # printer_data/comms
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    os.fchmod(sock.fileno(), 0o600)  # Linux: the socket file takes this mode when bound
    sock.bind(str(path))
    os.chmod(path, 0o600)
    sock.listen(64)
    sock.setblocking(False)
    return sock


def _log_file() -> dict[str, str]:
    """``log_file``: the file motiond logs to (``--log-file``), which Moonraker serves as
    ``klippy.log`` (the front-ends' log buttons); nothing when it logs to stderr only."""
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            return {"log_file": handler.baseFilename}
    return {}


def _host_stats() -> dict[str, float]:
    """Klipper's ``system_stats``: load, this process' CPU seconds, available memory (kB)."""
    pages = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return {"sysload": round(os.getloadavg()[0], 2), "cputime": round(time.process_time(), 3),
            "memavail": pages // 1024}
