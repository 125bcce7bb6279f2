"""The processes of ``python -m benchmarks klipper``: the klipper-avr rig, and a host driving it.

Both hosts get the same machine: X and Y on the pins of motiond's rig tests (80 steps/mm,
200 mm/s, 2,000 mm/s², 0-300 mm), a hardware-PWM laser on PB4 with a 1 s firmware watchdog,
the same cornering (motiond's junction deviation 0.01 mm is Klipper's square corner velocity
sqrt(0.01 · 2000 / (√2 - 1)) = 6.95 mm/s) and no minimum cruise ratio (motiond has none).

* :class:`Motiond`: ``python -m server.cli`` (it takes SCHED_FIFO itself, as ``serve`` does);
  G-code streamed by the streaming benchmark's client process, character counting over TCP;
* :class:`Klippy`: Klipper's own host at the firmware's commit (``scripts/klippy-host`` builds
  it under build/), under ``chrt -f 10`` when allowed; G-code through its API socket (``-a``),
  ``gcode/script`` ending in ``M400`` (answered when the moves are done).

The host's CPU is its own process's (every thread's run time from ``/proc``): not the sender's,
not the simulator's.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

from benchmarks.common import REPO
from benchmarks.streaming_support import run_client

RIGS = Path(os.environ.get("MOTIOND_RIGS", REPO.parent / "shared" / "rigs"))
KLIPPER_AVR = RIGS / "klipper-avr"
STEPS_PER_MM, MAX_RATE_MM_S, ACCEL_MM_S2, TRAVEL_MM = 80.0, 200.0, 2000.0, 300.0
JUNCTION_DEVIATION_MM = 0.01
SQUARE_CORNER_MM_S = math.sqrt(JUNCTION_DEVIATION_MM * ACCEL_MM_S2 / (math.sqrt(2) - 1))
LASER_S_MAX = 1000
RT_PRIORITY = 10  # motiond's [stepgen] realtime_priority default
POLL_S = 0.1
CLOCK_TICKS_HZ = os.sysconf("SC_CLK_TCK")
PAUSE_EVERY_S = 1.5  # --rig-pause-ms: how often the simulator is stopped
RUN_LIMIT_S = 60.0  # a job (a few seconds of motion) not done in this long has failed


def cpu_ns(pid: int) -> int:
    """Run time so far of every thread of a process and of every process it started (live:
    the scheduler's own count in ns; ended and reaped: their parent's ``cutime`` + ``cstime``,
    in clock ticks): motiond's job plans run in children of its forkserver."""
    total = 0
    for process in (pid, *_descendants(pid)):
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{process}/task").iterdir():
                with contextlib.suppress(OSError):
                    total += int((task / "schedstat").read_text().split()[0])
            fields = Path(f"/proc/{process}/stat").read_text().rpartition(")")[2].split()
            total += (int(fields[13]) + int(fields[14])) * 1_000_000_000 // CLOCK_TICKS_HZ
    return total


@dataclass(frozen=True)
class Threads:
    """A process's own threads, so far: its main thread's run time (ns) and how many times it
    was put on a CPU (``schedstat``'s third field: wake-ups, and resumptions after a
    preemption), and the same count for each of its other threads. motiond's main thread is
    its event loop's, klippy's its reactor's; the others are chiefly each host's serial
    thread."""

    main_ns: int = 0
    main_runs: int = 0
    others: dict[int, int] = field(default_factory=dict)  # thread id: runs

    @property
    def other_runs(self) -> int:
        return sum(self.others.values())

    def __sub__(self, before: Threads) -> Threads:
        """What ran since ``before`` (a thread that ended meanwhile is not counted)."""
        return Threads(self.main_ns - before.main_ns, self.main_runs - before.main_runs,
                       {tid: runs - before.others.get(tid, 0)
                        for tid, runs in self.others.items()})


def threads(pid: int) -> Threads:
    """:class:`Threads` of process ``pid`` now."""
    main_ns = main_runs = 0
    others: dict[int, int] = {}
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError, ValueError):
                run_ns, _, runs = (int(v) for v in (task / "schedstat").read_text().split())
                if task.name == str(pid):
                    main_ns, main_runs = run_ns, runs
                else:
                    others[int(task.name)] = runs
    return Threads(main_ns, main_runs, others)


def _descendants(pid: int) -> list[int]:
    parents: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                ppid = int((entry / "stat").read_text().rpartition(")")[2].split()[1])
                parents.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        children = parents.get(todo.pop(), [])
        found += children
        todo += children
    return found


@dataclass
class Rig:
    process: asyncio.subprocess.Process
    path: str
    gpio_log: Path
    serial_log: Path


async def pause_now_and_then(pid: int, pause_ms: float) -> None:
    """Stop the simulator for ``pause_ms`` every ``PAUSE_EVERY_S``: it then runs flat out until
    it has caught up with the wall clock, as it does on a loaded host (``LAG`` records)."""
    try:
        while True:
            await asyncio.sleep(PAUSE_EVERY_S)
            os.kill(pid, signal.SIGSTOP)
            try:
                await asyncio.sleep(pause_ms / 1e3)
            finally:
                os.kill(pid, signal.SIGCONT)
    except ProcessLookupError:
        return


@contextlib.asynccontextmanager
async def klipper_rig(workdir: Path, name: str, pause_ms: float = 0.0) -> AsyncIterator[Rig]:
    """The stock firmware in simavr, logging its pins and its serial bytes (``pause_ms``:
    stopped that long now and then, see :func:`pause_now_and_then`)."""
    gpio, serial = workdir / f"{name}-gpio.log", workdir / f"{name}-serial.log"
    stderr = (workdir / f"{name}-rig.err").open("wb")
    process = await asyncio.create_subprocess_exec(
        str(KLIPPER_AVR / "run"), stdout=asyncio.subprocess.PIPE, stderr=stderr,
        env={**os.environ, "MCU_GPIO_LOG": str(gpio), "MCU_SERIAL_LOG": str(serial)})
    stderr.close()
    try:
        assert process.stdout is not None
        path = (await asyncio.wait_for(process.stdout.readline(), 10.0)).decode().strip()
        if not path.startswith("/dev/"):
            raise RuntimeError(f"the rig printed {path!r}")
        async with asyncio.TaskGroup() as group:
            pauses = group.create_task(pause_now_and_then(process.pid, pause_ms)) \
                if pause_ms > 0 else None
            try:
                yield Rig(process, path, gpio, serial)
            finally:
                if pauses is not None:
                    pauses.cancel()
    finally:
        await stop(process)


async def stop(process: asyncio.subprocess.Process) -> None:
    if process.returncode is None:
        process.terminate()
        try:
            await asyncio.wait_for(process.wait(), 10.0)
        except TimeoutError:
            process.kill()
            await process.wait()


def pwm_configured(gpio_log: Path) -> bool:
    """Whether the firmware has set up timer 0's PWM (``config_pwm_out`` on PB4) yet."""
    with contextlib.suppress(OSError):
        for line in gpio_log.read_text().splitlines():
            words = line.split()
            if len(words) >= 5 and words[1] == "OCR0" and words[4] != "00":
                return True
    return False


def chrt_prefix() -> list[str]:
    """``chrt -f 10`` where this process may give real-time priority, else nothing."""
    allowed = subprocess.run(["chrt", "-f", str(RT_PRIORITY), "true"],
                             capture_output=True, check=False).returncode == 0
    return ["chrt", "-f", str(RT_PRIORITY)] if allowed else []


# -- motiond -----------------------------------------------------------------------------------
def motiond_toml(serial: str, data_dir: Path, lead_time_s: float | None = None) -> str:
    axes = "".join(f"[axes.{a}]\nsteps_per_mm = {STEPS_PER_MM}\nmax_rate_mm_s = {MAX_RATE_MM_S}\n"
                   f"accel_mm_s2 = {ACCEL_MM_S2}\nmax_mm = {TRAVEL_MM}\n" for a in "xy")
    return f"""[machine]
laser_mode = true
{axes}[planner]
junction_deviation_mm = {JUNCTION_DEVIATION_MM}
[jobs]
data_dir = '{data_dir}'
[http]
enabled = false
[backend]
kind = "klipper"
serial = "{serial}"
{f"lead_time_s = {lead_time_s}" if lead_time_s else ""}
[backend.axes.x]
step_pin = "PA0"
dir_pin = "!PA1"
enable_pin = "!PA2"
[backend.axes.y]
step_pin = "PA3"
dir_pin = "PA4"
[backend.outputs.PB4]
cycle_time_s = 0.0001
max_duration_s = 1.0
[laser]
pin = "PB4"
maximum_s_value = {LASER_S_MAX}
"""


class Motiond:
    name = "motiond"

    def __init__(self, process: asyncio.subprocess.Process, port: int, workdir: Path,
                 source: Path) -> None:
        self.process, self.port, self.workdir, self.source = process, port, workdir, source
        self._poll: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    @classmethod
    @contextlib.asynccontextmanager
    async def start(cls, rig: Rig, workdir: Path, source: Path = REPO,
                    lead_time_s: float | None = None,
                    log_level: str = "warning") -> AsyncIterator[Self]:
        toml = motiond_toml(rig.path, workdir / "data", lead_time_s)
        async with cls.serving(toml, workdir, source, rig, log_level) as host:
            yield host

    @classmethod
    @contextlib.asynccontextmanager
    async def serving(cls, config_text: str, workdir: Path, source: Path,
                      rig: Rig | None = None, log_level: str = "warning") -> AsyncIterator[Self]:
        """:meth:`spawn`, ready (on ``rig``, if given), stopped at the end."""
        (workdir / "data").mkdir(exist_ok=True)
        host = await cls.spawn(config_text, workdir, source, log_level)
        try:
            await host.wait_ready(rig)
            yield host
        finally:
            if host._poll is not None:
                host._poll[1].close()
            await stop(host.process)

    @classmethod
    async def spawn(cls, config_text: str, workdir: Path, source: Path,
                    log_level: str = "warning") -> Self:
        """``python -m server.cli`` of ``source`` on ``config_text``, on a free TCP port
        (``log_level`` debug: a line for each clock poll, which the benchmark can check)."""
        from tests.support.processes import free_port  # noqa: PLC0415

        config = workdir / "motiond.toml"
        config.write_text(config_text)
        port = free_port()
        with (workdir / "motiond.err").open("wb") as err:
            process = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "server.cli", "--config", str(config), "--host",
                "127.0.0.1", "--tcp-port", str(port), "--log-level", log_level, cwd=source,
                env={**os.environ, "PYTHONPATH": str(source)},
                stdout=asyncio.subprocess.DEVNULL, stderr=err)
        return cls(process, port, workdir, source)

    @property
    def pid(self) -> int:
        return self.process.pid

    async def status(self) -> str:
        """A ``?`` on one connection kept open (a connection per poll would cost motiond an
        accept, a banner and a close ten times a second: CPU that is not the job's)."""
        if self._poll is None:
            self._poll = await asyncio.open_connection("127.0.0.1", self.port)
        reader, writer = self._poll
        try:
            writer.write(b"?")
            while not (line := await asyncio.wait_for(reader.readline(), 5.0)).startswith(b"<"):
                pass
            return line.decode().strip()
        except (OSError, TimeoutError):
            writer.close()
            self._poll = None
            raise

    async def wait_ready(self, rig: Rig | None, limit_s: float = 30.0) -> None:
        """Until the board, if any, is configured (its PWM timer set up) and motiond is idle."""
        deadline = time.monotonic() + limit_s
        while True:
            with contextlib.suppress(OSError, TimeoutError):
                if ((rig is None or pwm_configured(rig.gpio_log))
                        and (await self.status()).startswith("<Idle")):
                    return
            if time.monotonic() > deadline or self.process.returncode is not None:
                raise RuntimeError("motiond never became ready (motiond.err)")
            await asyncio.sleep(0.2)

    async def recover(self, rig: Rig) -> None:
        """After an alarm: ``$X`` (which restarts the board when it was shut down), then idle."""
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        writer.write(b"$X\n")
        with contextlib.suppress(TimeoutError):
            while not (await asyncio.wait_for(reader.readline(), 10.0)).startswith(
                    (b"ok", b"error")):
                pass
        writer.close()
        await self.wait_ready(rig)

    async def play(self, lines: list[str], end_mm: tuple[float, float]) -> None:
        """The lines as a stored job, started with ``play`` (a print from Mainsail's file
        list, klippy's virtual SD card: the host has the whole job, as klippy's script);
        back when the job's end message came and motiond is idle at ``end_mm``."""
        jobs = self.workdir / "data" / "jobs"
        jobs.mkdir(parents=True, exist_ok=True)
        (jobs / "job.nc").write_text("\n".join(["G21 G90 G94", *lines]) + "\n")
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        try:
            writer.write(b"play job.nc\n")
            deadline = time.monotonic() + RUN_LIMIT_S
            while not (line := await asyncio.wait_for(reader.readline(), RUN_LIMIT_S)
                       ).startswith(b"[MSG:job job.nc done"):
                if line.startswith((b"error", b"ALARM", b"[MSG:job job.nc stopped")):
                    raise RuntimeError(f"motiond: {line.decode().strip()}")
                if time.monotonic() > deadline:
                    raise TimeoutError("the job did not end")
        finally:
            writer.close()
        await self._until_idle_at(end_mm, deadline)

    async def warm_up(self) -> None:
        """Play a stored job big enough to be planned in a child process (over
        ``IN_THREAD_BYTES``): a server's first such job starts the fork server the plans are
        forked from (an interpreter's start-up, once in the server's life), which the jobs
        measured after it do not pay. It stays where it is."""
        from server.jobs.planning import IN_THREAD_BYTES  # noqa: PLC0415

        line = "G1 X10.000 Y10.000 F6000"
        await self.play([line] * (IN_THREAD_BYTES // len(line) + 100), (10.0, 10.0))

    async def run(self, lines: list[str], end_mm: tuple[float, float]) -> None:
        """Stream the lines and ``M400`` (answered when the moves are done, as klippy's run is:
        neither host is polled while it moves); back when motiond is idle at ``end_mm``."""
        path = self.workdir / "job.nc"
        path.write_text("\n".join(["G21 G90 G94", *lines, "M400"]) + "\n")
        result = await run_client(self.port, path, banner=True)
        if result["errors"]:
            raise RuntimeError(f"motiond refused {result['errors']} lines")
        await self._until_idle_at(end_mm, time.monotonic() + RUN_LIMIT_S)

    async def _until_idle_at(self, end_mm: tuple[float, float], deadline: float) -> None:
        """Until motiond reports Idle at ``end_mm``; an alarm (with its log) or the deadline
        (monotonic) raises."""
        want = f"MPos:{end_mm[0]:.3f},{end_mm[1]:.3f}|"
        while not ((report := await self.status()).startswith("<Idle") and want in report):
            if time.monotonic() > deadline:
                raise TimeoutError(f"motiond not idle at {want}: {report}")
            if report.startswith("<Alarm"):
                log = (self.workdir / "motiond.err").read_text().strip().splitlines()[-3:]
                raise RuntimeError(f"{report} {' / '.join(log)}")
            await asyncio.sleep(POLL_S)


# -- klippy ------------------------------------------------------------------------------------
def printer_cfg(serial: str) -> str:
    def stepper(name: str, step: str, dir_: str, enable: str, endstop: str) -> str:
        return (f"[stepper_{name}]\nstep_pin: {step}\ndir_pin: {dir_}\n{enable}"
                f"microsteps: 16\nrotation_distance: {16 * 200 / STEPS_PER_MM}\n"
                f"endstop_pin: {endstop}\nposition_endstop: 0\nposition_max: {TRAVEL_MM}\n\n")

    return (f"[mcu]\nserial: {serial}\nbaud: 250000\nrestart_method: command\n\n"
            f"[printer]\nkinematics: cartesian\nmax_velocity: {MAX_RATE_MM_S}\n"
            f"max_accel: {ACCEL_MM_S2}\nminimum_cruise_ratio: 0\n"
            f"square_corner_velocity: {SQUARE_CORNER_MM_S:.4f}\n"
            "max_z_velocity: 10\nmax_z_accel: 100\n\n"
            + stepper("x", "PA0", "!PA1", "enable_pin: !PA2\n", "PC2")
            + stepper("y", "PA3", "PA4", "", "PC3")
            + stepper("z", "PA5", "PA6", "", "PC4")
            + "[force_move]\nenable_force_move: True\n\n"
            "[pwm_tool laser]\npin: PB4\nhardware_pwm: True\ncycle_time: 0.0001\n"
            "maximum_mcu_duration: 1.0\n")


def klippy_folder() -> Path:
    """Klipper's host, built under build/ by ``scripts/klippy-host`` (once)."""
    out = subprocess.run([str(REPO / "scripts" / "klippy-host")], check=True,
                         capture_output=True, text=True).stdout
    return Path(out.strip().splitlines()[-1])


class Klippy:
    name = "klippy"

    def __init__(self, process: asyncio.subprocess.Process, socket_path: Path) -> None:
        self.process, self.socket_path, self._id = process, socket_path, 0

    @classmethod
    @contextlib.asynccontextmanager
    async def start(cls, rig: Rig, workdir: Path) -> AsyncIterator[Klippy]:
        folder = klippy_folder()
        python = folder.parent.parent / "klippy-venv" / "bin" / "python"
        config, sock = workdir / "printer.cfg", workdir / "klippy.sock"
        config.write_text(printer_cfg(rig.path))
        process = await asyncio.create_subprocess_exec(
            *chrt_prefix(), str(python), str(folder / "klippy.py"), str(config),
            "-a", str(sock), "-l", str(workdir / "klippy.log"),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        host = cls(process, sock)
        try:
            await host.wait_ready()
            await host.request("gcode/script", script="SET_KINEMATIC_POSITION X=0 Y=0 Z=0")
            yield host
        finally:
            await stop(process)

    @property
    def pid(self) -> int:
        return self.process.pid

    async def request(self, method: str, timeout_s: float = RUN_LIMIT_S,
                      **params: object) -> object:
        reader, writer = await asyncio.open_unix_connection(str(self.socket_path),
                                                            limit=1 << 24)
        try:
            self._id += 1
            writer.write(json.dumps({"id": self._id, "method": method,
                                     "params": params}).encode() + b"\x03")
            reply = json.loads((await asyncio.wait_for(reader.readuntil(b"\x03"),
                                                       timeout_s))[:-1])
        finally:
            writer.close()
        if "error" in reply:
            raise RuntimeError(f"klippy: {reply['error']}")
        return reply.get("result")

    async def wait_ready(self, limit_s: float = 60.0) -> None:
        deadline = time.monotonic() + limit_s
        while True:
            with contextlib.suppress(OSError, RuntimeError, TimeoutError,
                                     asyncio.IncompleteReadError):
                info = await self.request("info", timeout_s=5.0)
                if isinstance(info, dict) and info.get("state") == "ready":
                    return
            if time.monotonic() > deadline or self.process.returncode is not None:
                raise RuntimeError("klippy never became ready on the rig (klippy.log)")
            await asyncio.sleep(0.2)

    async def recover(self, rig: Rig) -> None:
        """After an error or a shutdown: ``FIRMWARE_RESTART``, ready, at X0 Y0 again."""
        with contextlib.suppress(RuntimeError, OSError, asyncio.IncompleteReadError):
            await self.request("gcode/script", timeout_s=10.0, script="FIRMWARE_RESTART")
        await asyncio.sleep(1.0)
        await self.wait_ready()
        await self.request("gcode/script", script="SET_KINEMATIC_POSITION X=0 Y=0 Z=0")

    async def run(self, lines: list[str], end_mm: tuple[float, float]) -> None:
        """One ``gcode/script`` of the lines and ``M400``: answered when the moves are done."""
        await self.request("gcode/script", script="\n".join(["G21", "G90", *lines, "M400"]))
