"""``[klippy_api]``: Klipper's API socket, so Moonraker and its front-ends drive motiond.

    [klippy_api]
    socket = "/run/motiond/klippy_uds"

motiond serves Klipper's "webhooks" API (JSON objects ended by ``\\x03``, see
:mod:`modules.klippy_api.wire`) on that Unix socket; Moonraker's ``klippy_uds_address`` points
at it, and Mainsail, Fluidd, KlipperScreen and Home Assistant's Moonraker integration then show
and drive this machine. The socket is created owner-only (mode 0600, set before it exists):
whoever can open it controls the machine, like a token holder.

Each connection is a :class:`~modules.klippy_api.session.Session`; the printer objects come
from :mod:`modules.klippy_api.objects`. Subscribers get what changed at most ``status_hz``
times a second. Messages the machine pushes to every sender (alarms, ``[MSG:...]``) go to the
G-code output subscribers. A client that does not read (``OUTGOING_LIMIT`` messages waiting) is
disconnected.
"""

from __future__ import annotations

import asyncio
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
from modules.klippy_api import wire
from modules.klippy_api.gcode import HELP
from modules.klippy_api.session import Session, response_text
from server import __version__
from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.paths import jobs_dir
from server.runtime.events import Event

# Klipper's source folder as Moonraker reads it: its config/ and docs/ (README files that
# point at motiond's), so Moonraker's config_examples and docs roots are valid folders.
KLIPPER_PATH = Path(__file__).resolve().parent / "klipper"
OUTGOING_LIMIT = 1000
READ_BYTES = 65536


class KlippyApiConfig(ModuleConfig):
    socket: Path = Field(description="the Unix socket Moonraker's klippy_uds_address names")
    status_hz: float = Field(4.0, gt=0, le=50, description="subscription pushes per second")


class _Connection:
    def __init__(self, writer: asyncio.StreamWriter) -> None:
        self.writer = writer
        self.outgoing: asyncio.Queue[bytes] = asyncio.Queue(OUTGOING_LIMIT)
        self.session: Session | None = None

    def send(self, message: dict[str, Any]) -> None:
        try:
            self.outgoing.put_nowait(wire.encode(message))
        except asyncio.QueueFull:
            self.writer.close()  # it does not read: dropped, never waited for


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
        self.connections: set[_Connection] = set()
        ctx.subscribe(Event.PUSH, lambda message: self.output(response_text(str(message))))
        ctx.subscribe(Event.JOB, self._on_job)
        for event in (Event.STATE, Event.HALT, Event.CLEAR_HALT):
            ctx.subscribe(event, lambda *_: self._push_all())

    # -- Hub --------------------------------------------------------------------------------
    def objects(self) -> dict[str, Any]:
        self.extra.host = _host_stats()
        self.extra.durations_s = self.times.durations(self.ctx.clock.now_s())
        return printer.build_objects(self.ctx.status(), self.machine, self.extra)

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
            if connection.session is not None:
                connection.session.push_output(text)

    def restart(self) -> None:
        """After RESTART/FIRMWARE_RESTART: the last job is forgotten (``print_stats`` is
        ``standby``, as after Klipper's restart) and every connection closes."""
        job = self.ctx.status().get("job") or {}
        if job:
            self.extra.forgotten_job = (str(job["name"]), float(job["started_s"]))
        for connection in list(self.connections):
            connection.writer.close()

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
        period_s = 1.0 / self.config.status_hz
        while True:
            await asyncio.sleep(period_s)
            self._push_all()

    def _push_all(self) -> None:
        """Push what changed to every subscriber (on a tick, and at once when the machine's
        or the job's state changes: a pause and resume between two ticks is two changes)."""
        sessions = [c.session for c in self.connections
                    if c.session is not None and c.session.subscription]
        if sessions:
            now = self.objects()
            for session in sessions:
                session.push_status(now)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        connection = _Connection(writer)
        session = connection.session = Session(self, connection.send)
        self.connections.add(connection)
        framer = wire.Framer()
        try:
            async with asyncio.TaskGroup() as group:
                sender = group.create_task(_drain(connection), name="klippy-api-send")
                scripts = group.create_task(session.run_scripts(), name="klippy-api-scripts")
                try:
                    while data := await reader.read(READ_BYTES):
                        for request in framer.feed(data):
                            session.on_request(request)
                except (wire.FramingError, ConnectionError) as exc:
                    self.ctx.log.warning("API client dropped: %s", exc)
                sender.cancel()
                scripts.cancel()
        finally:
            self.connections.discard(connection)
            writer.close()

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
        self._push_all()


async def _drain(connection: _Connection) -> None:
    writer = connection.writer
    try:
        while True:
            data = await connection.outgoing.get()
            writer.write(data)
            await writer.drain()
    except ConnectionError:
        writer.close()  # the reader then ends the connection


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
    sock.listen(8)
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
