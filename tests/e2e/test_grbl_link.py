"""``[backend] kind = "grbl"``: motiond as the networked host of a Grbl controller, end to end.

The controller is a real Grbl-speaking program on a real pseudo-terminal: a second motiond (its
simulated machine) started as a subprocess with ``--pty``. The motiond under test runs
in-process with ``[backend] kind = "grbl"`` on that pty, and real senders drive it: grbl-streamer
over its own pty, printrun's printcore and a character-counting client over TCP. The checks are
on the controller itself (asked directly over its own TCP port): it ends at the exact position
the job commands; every line gets one reply, in order, the controller's errors included; hold,
resume, overrides and reset reach it within a status period; ten clients polling ``?`` cost the
board no more polls than one; killing the controller mid-job alarms, stops the job, and a new
controller on the same path is reconnected, unlocked with ``$X`` and runs the job again.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from server.api.telemetry import build_status
from server.app import App
from server.backends.grbl.machine import GrblMachine
from server.backends.grbl.reports import parse_status
from server.config import Config
from server.config_loader import build_config
from server.runtime.clock import RealClock
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport
from tests.support.helpers import running
from tests.support.processes import Served, motiond
from tests.support.senders import (
    BANNER,
    CharCountingClient,
    GrblStreamerRun,
    PrintcoreRun,
    expected_run,
    wait_for,
)

# The controller: fast enough that a few hundred short moves run in a few seconds.
CONTROLLER_AXES = "".join(
    f"[axes.{axis}]\nsteps_per_mm = 80\nmax_rate_mm_s = 1000\naccel_mm_s2 = 50000\n"
    "min_mm = -50\nmax_mm = 300\n" for axis in "xyz")
CONTROLLER_PROBE = "[backend]\nprobe_at_mm = { z = -2.0 }\n"  # its probe touches at Z-2
STATUS_HZ = 20


pytestmark = pytest.mark.usefixtures("quick_thread_switches")


def job(count: int = 240) -> list[str]:
    """Short moves in a small square, comments, blank lines and spindle words."""
    lines = ["G21 G90 (metric, absolute)", "", "G0 X1 Y1", "M3 S200 ; laser on"]
    for index in range(count):
        x = 1 + (index * 7 % 13) * 0.25
        y = 1 + (index * 11 % 17) * 0.25
        lines.append(f"G1 X{x:.3f} Y{y:.3f} F{30000 + index % 5 * 1000}")
    return [*lines, "M5", "G0 X3.25 Y4.5"]


def link_config(tmp_path: Path, **sections: Any) -> Config:
    """The motiond under test: axes deliberately unlike the controller's (it adopts those)."""
    data: dict[str, Any] = {
        "axes": {axis: {"steps_per_mm": 100, "max_rate_mm_s": 100, "accel_mm_s2": 1000,
                        "min_mm": -50, "max_mm": 300} for axis in "xyz"},
        "jobs": {"data_dir": str(tmp_path / "link-data")},
        "backend": {"kind": "grbl", "serial": str(tmp_path / "ttyController"),
                    "status_hz": STATUS_HZ, "reconnect_s": 0.2},
        "serial": {"pty": str(tmp_path / "ttyLink")},
        "tcp": {"port": 0},
    }
    data.update(sections)
    return build_config(data, "link.toml")


@contextlib.asynccontextmanager
async def controller(tmp_path: Path) -> AsyncIterator[Served]:
    async with motiond(tmp_path, CONTROLLER_PROBE, axes_toml=CONTROLLER_AXES, name="controller",
                       args=["--pty", str(tmp_path / "ttyController")]) as served:
        yield served


@contextlib.asynccontextmanager
async def link(tmp_path: Path, **sections: Any) -> AsyncIterator[App]:
    async with running(link_config(tmp_path, **sections), RealClock(),
                       [TcpTransport, SerialTransport]) as app:
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        await wait_for(lambda: machine.controller.ready, 10.0, "the controller's handshake")
        yield app


def tcp_port(app: App) -> int:
    port: int = app.transports[0].port  # type: ignore[attr-defined]
    return port


async def controller_report(served: Served) -> str:
    """The controller's own status report, asked over its own TCP port."""
    reader, writer = await asyncio.open_connection("127.0.0.1", served.tcp_port)
    try:
        while (await asyncio.wait_for(reader.readline(), 5)).decode().strip() != BANNER:
            pass
        writer.write(b"?")
        while True:
            line = (await asyncio.wait_for(reader.readline(), 5)).decode().strip()
            if line.startswith("<"):
                return line
    finally:
        writer.close()


async def controller_settles_at(served: Served, end_mm: tuple[float, ...],
                                tolerance_mm: float = 0.0) -> None:
    """The controller reports Idle at exactly ``end_mm`` (three decimals, as it prints; within
    ``tolerance_mm`` for a position that three decimals cannot hold)."""
    deadline = time.monotonic() + 20
    while True:
        status = parse_status(await controller_report(served))
        expected = tuple(round(v, 3) for v in end_mm)
        if status.state == "Idle" and all(
                abs(a - b) <= tolerance_mm + 1e-9 for a, b in zip(status.machine_mm, expected,
                                                                 strict=True)):
            return
        assert time.monotonic() < deadline, f"controller at {status}, not Idle at {end_mm}"
        await asyncio.sleep(0.05)


class Listener:
    """A connection that only reads (and can send realtime bytes): an observer."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.lines: list[str] = []
        self._task = asyncio.create_task(self._read())

    @classmethod
    async def connect(cls, port: int) -> Listener:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        return cls(reader, writer)

    async def _read(self) -> None:
        while line := await self.reader.readline():
            self.lines.append(line.decode().strip())

    async def expect(self, what: str, timeout_s: float = 10.0) -> str:
        def found() -> bool:
            return any(what in line for line in self.lines)

        await wait_for(found, timeout_s, repr(what))
        return next(line for line in self.lines if what in line)

    async def state(self, prefix: str, timeout_s: float = 5.0, containing: str = "") -> float:
        """Poll ``?`` until the report starts with ``<prefix`` (and holds ``containing``);
        returns the seconds it took."""
        started = time.monotonic()
        while True:
            self.lines.clear()
            self.writer.write(b"?")
            await asyncio.sleep(0.02)
            if any(line.startswith(f"<{prefix}") and containing in line for line in self.lines):
                return time.monotonic() - started
            assert time.monotonic() - started < timeout_s, f"never {prefix}: {self.lines}"

    async def close(self) -> None:
        self._task.cancel()
        self.writer.close()


# -- streaming with real senders -------------------------------------------------------------------
async def test_grbl_streamer_through_motiond_ends_the_controller_at_the_exact_position(
        tmp_path: Path) -> None:
    lines = job()
    async with controller(tmp_path) as served, link(tmp_path) as app:
        core = app.kernel.config.core
        # adopted from the controller's $$: steps, rates and accelerations are the board's
        assert [a.steps_per_mm for a in core.axes.values()] == [80, 80, 80]
        assert [a.max_rate_mm_s for a in core.axes.values()] == [1000, 1000, 1000]
        assert [a.accel_mm_s2 for a in core.axes.values()] == [50000, 50000, 50000]
        sender = GrblStreamerRun()
        try:
            await sender.connect(str(tmp_path / "ttyLink"))
            await sender.run_job(lines, timeout_s=60.0)
        finally:
            await sender.close()
        assert not sender.errors and not sender.alarms
        assert sender.processed == len(sender.sent), "a job line was never acknowledged"
        assert sender.oks == len(sender.writes), "one ok per line written, no more, no less"
        end_mm = expected_run(lines, core).end_mm
        await controller_settles_at(served, end_mm)
        # the web UI's live position is the board's
        end = [round(v, 3) for v in end_mm]
        await wait_for(lambda: build_status(app.kernel)["mpos"] == end, 2.0, "the UI at the end")
        assert build_status(app.kernel)["state"] == "Idle"


async def test_printcore_over_tcp_through_motiond(tmp_path: Path) -> None:
    lines = job(120)
    async with controller(tmp_path) as served, link(tmp_path) as app:
        sender = PrintcoreRun()
        try:
            await sender.connect(f"127.0.0.1:{tcp_port(app)}")
            await sender.run_job(lines, timeout_s=60.0)
        finally:
            await sender.close()
        assert sender.refusals() == [] and sender.host_errors == []
        assert sender.oks == len(sender.sent), "one ok per line sent"
        await controller_settles_at(served, expected_run(lines, app.kernel.config.core).end_mm)


async def test_replies_are_one_per_line_in_order_with_local_and_controller_errors(
        tmp_path: Path) -> None:
    lines = job(150)
    local_error, controller_error = 40, 90
    lines.insert(local_error, "G1 X2 Y")  # motiond's interpreter refuses it: never sent
    lines.insert(controller_error, "M106 S100")  # motiond has a fan; the controller has not
    fan = {"switch": {"fan": {"pin": "fan", "on_mcode": 106, "off_mcode": 107}}}
    async with controller(tmp_path) as served, link(tmp_path, **fan) as app:
        observer = await Listener.connect(tcp_port(app))
        client = await CharCountingClient.connect("127.0.0.1", tcp_port(app))
        try:
            result = await client.stream(lines)
        finally:
            await client.close()
        assert result.extra_replies == 0 and len(result.replies) == len(lines)
        refused = {index: reply for index, reply in enumerate(result.replies) if reply != "ok"}
        assert refused == {local_error: "error:2", controller_error: "error:20"}
        assert result.max_unacked_bytes > 60, "several lines were in flight at once"
        await observer.expect("[MSG:controller error:20 on M106S100]")
        await observer.close()
        valid = [line for index, line in enumerate(lines) if index != local_error]
        await controller_settles_at(served, expected_run(valid, app.kernel.config.core).end_mm)


# -- realtime bytes and status ---------------------------------------------------------------------
async def test_hold_resume_override_and_reset_reach_the_controller(tmp_path: Path) -> None:
    async with controller(tmp_path) as served, link(tmp_path) as app:
        client = await Listener.connect(tcp_port(app))
        await client.expect(BANNER)
        client.writer.write(b"G1 X200 F600\n")  # 20 s at 10 mm/s
        await client.state("Run")
        client.writer.write(b"!")
        took_s = await client.state("Hold")
        assert took_s < 1.0, "a hold shows within a status period (generous bound)"
        assert parse_status(await controller_report(served)).base_state == "Hold"
        client.writer.write(b"~")
        await client.state("Run")
        client.writer.write(b"\x91")  # feed +10 %
        # motiond keeps no override of its own on this backend: Ov: is the board's report
        await client.state("Run", containing="|Ov:110,")
        app.kernel.machine.set_overrides(feed=75, spindle=120)  # the API's machine.override
        await client.state("Run", containing="|Ov:75,100,120")
        client.writer.write(b"\x18")
        await client.expect("ALARM:3")  # Grbl: reset while moving
        stopped = parse_status(await controller_report(served))
        assert stopped.state == "Alarm"
        await asyncio.sleep(0.2)
        assert parse_status(await controller_report(served)).machine_mm == stopped.machine_mm
        client.lines.clear()
        client.writer.write(b"$X\n")
        await client.expect("ok")
        await client.state("Idle")
        await client.close()


async def test_ten_clients_polling_do_not_multiply_the_polls_of_the_board(
        tmp_path: Path) -> None:
    async with controller(tmp_path), link(tmp_path) as app:
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        clients = [await Listener.connect(tcp_port(app)) for _ in range(10)]
        before, started = machine.controller.status_polls, time.monotonic()
        for _ in range(25):  # each client at 50 Hz for half a second
            for client in clients:
                client.writer.write(b"?")
            await asyncio.sleep(0.02)
        elapsed_s = time.monotonic() - started
        polls = machine.controller.status_polls - before
        reports = [sum(line.startswith("<") for line in c.lines) for c in clients]
        for client in clients:
            await client.close()
        assert min(reports) >= 20, f"every client got its reports: {reports}"
        assert polls <= STATUS_HZ * elapsed_s + 3, f"{polls} polls of the board"


# -- pulling the cable --------------------------------------------------------------------------
async def test_killing_the_controller_mid_job_alarms_and_a_new_one_is_reconnected(
        tmp_path: Path) -> None:
    lines = job(400)
    (tmp_path / "link-data" / "jobs").mkdir(parents=True)
    (tmp_path / "link-data" / "jobs" / "job.gcode").write_text("\n".join(lines) + "\n")
    async with link_after_controller(tmp_path) as (served, app):
        client = await Listener.connect(tcp_port(app))
        client.writer.write(b"play job.gcode\n")
        await client.state("Run")
        served.process.kill()
        await served.process.wait()
        # the cable is out: the device node goes (udev removes /dev/ttyUSB0; here the link to
        # the dead pty, whose number another pty on this machine may take at any time)
        (tmp_path / "ttyController").unlink()
        await client.expect("ALARM:42")
        await client.expect("[MSG:job job.gcode stopped at")
        assert not app.kernel.jobs.active
        client.lines.clear()
        async with controller(tmp_path) as again:
            await client.expect("[MSG:controller connected")
            client.writer.write(b"$X\nplay job.gcode\n")
            await client.expect("[MSG:job job.gcode done", timeout_s=30)
            end_mm = expected_run(lines, app.kernel.config.core).end_mm
            await controller_settles_at(again, end_mm)
        await client.close()


@contextlib.asynccontextmanager
async def link_after_controller(tmp_path: Path) -> AsyncIterator[tuple[Served, App]]:
    async with controller(tmp_path) as served, link(tmp_path) as app:
        yield served, app


async def test_a_probe_waits_for_the_board_and_goes_on_from_where_it_stopped(
        tmp_path: Path) -> None:
    async with controller(tmp_path) as served, link(tmp_path) as app:
        client = await CharCountingClient.connect("127.0.0.1", tcp_port(app))
        try:
            report, reply = await client.command("G38.2 Z-10 F600")
            assert reply == "ok" and report.startswith("[PRB:0.000,0.000,-2.0")
            touched_z = float(report.split(",")[2].split(":")[0])  # within a tick of Z-2
            assert await client.command("G91 G0 Z1") == ["ok"]
            position = (await client.command("M114"))[0]
        finally:
            await client.close()
        end_z = round(touched_z * 80) / 80 + 1  # on the step grid (80 steps/mm: 0.0125 mm),
        # which [PRB:] prints with 3 decimals
        assert position.startswith("C: X:0.0000 Y:0.0000 Z:") and " MPos: X:0.0000 Y:0.0000 " \
            in position, position
        words = position.split()
        assert float(words[3][2:]) == float(words[-1][2:]) == pytest.approx(end_z, abs=1.1e-3)
        await controller_settles_at(served, (0.0, 0.0, end_z), tolerance_mm=1.1e-3)
        assert app.kernel.machine.interpreter.position == pytest.approx((0.0, 0.0, end_z),
                                                                        abs=1.1e-3)


async def test_a_controller_over_tcp_as_fluidnc_and_grblhal_offer(tmp_path: Path) -> None:
    lines = job(60)
    async with controller(tmp_path) as served:
        backend = {"kind": "grbl", "tcp": f"127.0.0.1:{served.tcp_port}", "status_hz": 5}
        async with link(tmp_path, backend=backend) as app:
            client = await CharCountingClient.connect("127.0.0.1", tcp_port(app))
            try:
                result = await client.stream(lines)
            finally:
                await client.close()
            assert result.replies == ["ok"] * len(lines)
            await controller_settles_at(served, expected_run(lines, app.kernel.config.core).end_mm)


async def test_after_ctrl_x_no_reply_of_a_dropped_line_reaches_the_client(
        tmp_path: Path) -> None:
    async with controller(tmp_path) as served, link(tmp_path) as app:
        client = await CharCountingClient.connect("127.0.0.1", tcp_port(app))
        try:
            # streamed ahead without counting: most of these are queued or in flight at the reset
            client.writer.write("".join(f"G1 X{n % 7 + 1} F3000\n" for n in range(60)).encode())
            await asyncio.sleep(0.05)
            client.writer.write(b"\x18")
            while (await client._line(5.0)) != BANNER:
                pass
            reply = await client.command("$G")  # a stale ok would end this before [GC:...]
            assert reply[-1] == "ok" and any(line.startswith("[GC:") for line in reply)
            assert (await client.command("$X"))[-1] == "ok"  # reset in motion: ALARM:3
            assert (await client.command("G0 X9"))[-1] == "ok"
        finally:
            await client.close()
        await controller_settles_at(served, (9.0, 0.0, 0.0))


async def test_the_boards_offsets_and_modes_are_adopted_and_settings_written_through(
        tmp_path: Path) -> None:
    async with controller(tmp_path) as served:
        board = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        try:  # set on the board itself, before motiond connects
            assert await board.command("G10 L2 P2 X10 Y20") == ["ok"]
            assert await board.command("G55") == ["ok"]
        finally:
            await board.close()
        async with link(tmp_path) as app:
            client = await CharCountingClient.connect("127.0.0.1", tcp_port(app))
            try:
                offsets = await client.command("$#")
                assert "[G55:10.000,20.000,0.000]" in offsets
                assert " G55 " in (await client.command("$G"))[0]
                assert await client.command("G0 X5 Y5") == ["ok"]  # work coordinates
                assert await client.command("$110=42000") == ["ok"]  # written to both
                assert (await client.command("$33=1"))[-1] == "error:3"  # the board's answer
            finally:
                await client.close()
            await controller_settles_at(served, (15.0, 25.0, 0.0))
        board = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        try:
            assert "$110=42000.000" in await board.command("$$")
        finally:
            await board.close()


async def test_a_jobs_remaining_time_follows_the_board_and_stands_still_in_a_hold(
        tmp_path: Path) -> None:
    (tmp_path / "link-data" / "jobs").mkdir(parents=True)
    slow = "G21 G90\nG1 X80 F600\nG0 X0\n"  # 8 s
    (tmp_path / "link-data" / "jobs" / "slow.gcode").write_text(slow)
    async with link_after_controller(tmp_path) as (served, app):
        client = await Listener.connect(tcp_port(app))
        client.writer.write(b"play slow.gcode\n")
        await client.state("Run")
        await asyncio.sleep(2.0)
        progress = app.kernel.jobs.progress()
        assert progress is not None and progress.estimate_s is not None
        assert progress.remaining_s is not None
        assert 1.0 < progress.estimate_s - progress.remaining_s < 4.0, progress
        client.writer.write(b"!")
        await client.state("Hold:0")
        held = app.kernel.jobs.progress().remaining_s  # type: ignore[union-attr]
        await asyncio.sleep(1.5)
        assert app.kernel.jobs.progress().remaining_s == held  # type: ignore[union-attr]
        client.writer.write(b"~")
        await client.expect("[MSG:job slow.gcode done", timeout_s=30)
        await client.close()
