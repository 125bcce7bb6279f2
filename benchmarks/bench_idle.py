"""What an idle server costs: CPU per second of wall time while nothing moves.

1. ``motiond`` as a user starts it (the embedded default: a laser with endstops and an air
   switch, the TCP and HTTP ports open, the loop monitor and the second ticker running), in a
   process of its own with its own data folder: its user + system CPU time from
   ``/proc/PID/stat`` over the window, after a warm-up.
2. The Klipper backend against the virtual MCU (``tests/support/virtual_mcu.py``, on a pty,
   in a thread of this process): the CPU time of the event loop's thread only
   (``time.thread_time`` on the loop), so the simulated board's own work is not counted. The
   backend's tick sleeps too while the board has nothing queued, moving or on; what remains is
   the clock synchronisation with the board.

Figures are percent of one core; goal: under 2 % for both.
"""

from __future__ import annotations

import asyncio
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.common import BenchResult, scratch_data_dir, standalone  # noqa: E402
from tests.support.processes import free_port  # noqa: E402


def process_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (``/proc/PID/stat`` fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_listening(port: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), 0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise TimeoutError(f"motiond did not listen on {port}")


def motiond_idle_percent(window_s: float, warmup_s: float) -> float:
    """A ``motiond`` process on the embedded default, idle: percent of a core."""
    data, tcp_port = scratch_data_dir(), free_port()
    env = {**os.environ, "XDG_CONFIG_HOME": data}  # no user config is picked up
    process = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "--data-dir", data, "--tcp-port", str(tcp_port),
         "--http-port", str(free_port()), "--log-level", "warning"],
        cwd=data, env={**env, "PYTHONPATH": str(REPO)},
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_listening(tcp_port)
        time.sleep(warmup_s)
        cpu_before, wall_before = process_cpu_s(process.pid), time.monotonic()
        time.sleep(window_s)
        cpu_s = process_cpu_s(process.pid) - cpu_before
        return 100.0 * cpu_s / (time.monotonic() - wall_before)
    finally:
        process.terminate()
        process.wait(10)


async def klipper_idle_percent(window_s: float, warmup_s: float) -> float:
    """The event loop thread's CPU with the Klipper backend on the virtual MCU, idle."""
    from server.app import App
    from server.backends.klipper.backend import KlipperBackend
    from server.config_loader import build_config
    from server.runtime.clock import RealClock
    from tests.support.virtual_mcu import VirtualMcu

    mcu = VirtualMcu().start()
    pins = {"x": {"step_pin": "PB13", "dir_pin": "!PB12", "enable_pin": "!PB14"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2", "enable_pin": "!PB11"}}
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000, "max_mm": 300}
            for a in "xy"}
    config = build_config({
        "axes": axes, "jobs": {"data_dir": scratch_data_dir()},
        "backend": {"kind": "klipper", "serial": mcu.path, "axes": pins,
                    "outputs": {"PA8": {"pwm": True, "cycle_time_s": 0.0002}}},
        "laser": {"pin": "PA8"}})
    app = App(config, clock=RealClock(), transports=[])
    task = asyncio.create_task(app.run())
    try:
        await app.ready.wait()
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        for _ in range(500):
            if backend.ready:
                break
            await asyncio.sleep(0.01)
        await asyncio.sleep(warmup_s)
        cpu_before, wall_before = time.thread_time(), time.monotonic()
        await asyncio.sleep(window_s)
        return 100.0 * (time.thread_time() - cpu_before) / (time.monotonic() - wall_before)
    finally:
        app.request_stop()
        await asyncio.wait_for(task, 10)
        mcu.stop()


def run(quick: bool) -> BenchResult:
    window_s, warmup_s = (4.0, 2.0) if quick else (20.0, 3.0)
    result = BenchResult("idle", quick)
    sim = motiond_idle_percent(window_s, warmup_s)
    klipper = asyncio.run(klipper_idle_percent(window_s, warmup_s))
    print(f"idle CPU over {window_s:g} s, percent of one core (goal: under 2 % for both)")
    print(f"  motiond, embedded default (simulated laser), whole process   {sim:6.2f} %")
    print(f"  Klipper backend on the virtual MCU, event loop thread       {klipper:6.2f} %")
    note = f"{window_s:g} s window after {warmup_s:g} s"
    result.add("idle", "motiond (sim)", note, cpu=(sim, "% of a core"))
    result.add("idle", "klipper backend (loop thread)", note, cpu=(klipper, "% of a core"))
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
