"""Faults with a defined outcome: a failing backend alarms and the server keeps answering;
SIGTERM mid-job stops motion, turns tools off and exits cleanly; a port in use is a clear error."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence

from server.backends.sim import SimBackend
from server.runtime.events import MachineState
from tests.conftest import REPO, make_config
from tests.support.helpers import running, submit_all


class FailingBackend(SimBackend):
    """A simulated machine whose step output breaks after a number of calls."""

    def __init__(self, *args, fail_after: int, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.calls = 0
        self.fail_after = fail_after

    def step(self, time_s: float, delta_steps: Sequence[int]) -> None:
        self.calls += 1
        if self.calls > self.fail_after:
            raise OSError(5, "stepper driver not responding")
        super().step(time_s, delta_steps)


async def test_a_failing_backend_alarms_stops_motion_turns_the_laser_off_and_keeps_serving(
) -> None:
    pushed: list[str] = []
    async with running(make_config(laser={})) as app:
        machine = app.kernel.machine
        backend = FailingBackend(("X", "Y", "Z"), (80, 80, 400), fail_after=200)
        machine.backend = machine.stepgen.backend = backend
        app.kernel.events.subscribe("push", pushed.append)
        await submit_all(app, ["M4 S800", "G1 X100 F3000", "G1 X0"])
        await app.clock.sleep(2.0)  # type: ignore[attr-defined]
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 42
        assert pushed[:1] == ["ALARM:42"]
        assert "stepper driver not responding" in pushed[1]
        assert pushed.count("ALARM:42") == 1, "a backend that keeps failing alarms once"
        assert not machine.stepgen.state.moving and len(machine.planner) == 0
        assert any(name == "laser" and value > 0 for _, name, value in backend.output_trace)
        assert backend.output("laser") == 0.0
        assert (await submit_all(app, ["$G"]))[0][0].startswith("[GC:")


def test_sigterm_mid_job_stops_and_exits_cleanly_within_two_seconds() -> None:
    process = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "--tcp-port", "0", "--http-port", "0",
         "--log-level", "info"],
        cwd=REPO, env={**os.environ, "PYTHONUNBUFFERED": "1"}, stderr=subprocess.PIPE, text=True)
    assert process.stderr is not None
    port = None
    deadline = time.monotonic() + 20
    while port is None and time.monotonic() < deadline:
        line = process.stderr.readline()
        if "TCP listening on" in line:
            port = int(line.rsplit(":", 1)[1])
    assert port is not None
    with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
        client.sendall(b"M4 S500\nG1 X300 F1200\nG1 Y200\nG1 X0\n")
        received = b""
        while received.count(b"ok") < 4:
            received += client.recv(4096)
        time.sleep(0.5)  # moving now
        started = time.monotonic()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=5) == 0
        assert time.monotonic() - started < 2.0
    rest = process.stderr.read()
    assert "Traceback" not in rest and "stopped" in rest


def test_a_port_another_program_holds_is_one_clear_line_and_exit_1() -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "server.cli", "--host", "127.0.0.1", "--tcp-port", str(port),
             "--http-port", "0", "--log-level", "warning"],
            cwd=REPO, env={**os.environ, "PYTHONUNBUFFERED": "1"}, capture_output=True,
            text=True, timeout=30)
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert f"motiond cannot start: [Errno 98] error while attempting to bind on address " \
           f"('127.0.0.1', {port}): address already in use" in done.stderr
