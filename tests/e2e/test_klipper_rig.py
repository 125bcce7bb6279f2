"""motiond drives the stock Klipper firmware (the klipper-avr rig: an atmega644p in simavr, in
real time) and the pins say what happened: an emergency stop mid-move leaves an alarm every
connection sees and the position the pins reached, recovery restarts the board and the next
move ends exactly where it should; a motiond killed mid-cut leaves the laser on no longer than
its watchdog allows, and the next motiond restarts the shut-down board and drives it."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from tests.support.klipper_rig import GpioLog, klipper_rig, wait_configured
from tests.support.processes import motiond
from tests.support.senders import CharCountingClient

MAX_DURATION_S = 0.5
LEAD_S = 0.2


def rig_toml(path: str) -> str:
    return f"""
[backend]
kind = "klipper"
serial = "{path}"
lead_time_s = {LEAD_S}
[backend.axes.x]
step_pin = "PA0"
dir_pin = "!PA1"
enable_pin = "!PA2"
[backend.axes.y]
step_pin = "PA3"
dir_pin = "PA4"
[backend.outputs.PB4]
max_duration_s = {MAX_DURATION_S}
[laser]
pin = "PB4"
maximum_s_value = 1000
"""


async def status(client: CharCountingClient) -> str:
    client.writer.write(b"?")
    while True:
        line = await asyncio.wait_for(client.reader.readline(), 10.0)
        if line.startswith(b"<"):
            return line.decode().strip()


async def until_idle(client: CharCountingClient, limit_s: float = 20.0) -> str:
    deadline = time.monotonic() + limit_s
    while not (report := await status(client)).startswith("<Idle"):
        assert time.monotonic() < deadline, report
        await asyncio.sleep(0.05)
    return report


def x_steps(gpio: GpioLog, after_cycle: int = 0) -> tuple[int, int]:
    """X's (gross, net) steps after ``after_cycle``; its dir pin is inverted (level 0 = +)."""
    rises = [c for c, v in gpio.edges.get("A0", []) if v == 1 and c > after_cycle]
    net = sum(-1 if gpio.level_at("A1", c) else 1 for c in rises)
    return len(rises), net


@pytest.mark.parametrize("stop", ["m112", "ctrl-x"])
async def test_an_emergency_stop_mid_move_alarms_everyone_keeps_the_pins_position_and_recovers(
    tmp_path: Path, stop: str
) -> None:
    async with klipper_rig(tmp_path) as board, motiond(tmp_path, rig_toml(board.path)) as served:
        await wait_configured(board)
        sender = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        watcher = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        result = await sender.stream(["G21 G90", "M3 S800", "G1 X100 F3000"])
        assert result.replies == ["ok"] * 3
        await asyncio.sleep(1.0)  # mid-move: X100 at 50 mm/s takes 2 s
        sender.writer.write(b"M112\n" if stop == "m112" else b"\x18")
        await asyncio.sleep(1.0)
        report = await status(watcher)
        gpio = board.gpio()
        gross, net = x_steps(gpio)
        assert 0 < net == gross < 8000, "stopped mid-move"
        assert report.startswith("<Alarm|MPos:") and f"MPos:{net / 80:.3f}," in report, (
            report, net)
        duties = gpio.pwm_pb4()
        assert max(d for _, d in duties) == 204 and duties[-1][1] == 0, duties
        replies = (await watcher.stream(["G1 X10"])).replies  # a client's replies add up
        assert replies[-1].startswith("error:"), replies
        assert x_steps(board.gpio())[0] == gross
        replies = (await watcher.stream(["$X"])).replies
        assert replies[-1] == "ok", replies
        replies = (await watcher.stream(["G1 X10 F3000"])).replies
        assert replies[-1] == "ok", replies
        report = await until_idle(watcher)
        await asyncio.sleep(0.1)
        assert "MPos:10.000," in report
        _, net = x_steps(board.gpio())
        assert net == 800, "the pins end exactly at X10"
        await sender.close()
        await watcher.close()


async def test_a_killed_motiond_leaves_the_laser_on_no_longer_than_its_watchdog_and_the_next_one_recovers_the_board(  # noqa: E501
    tmp_path: Path
) -> None:
    async with klipper_rig(tmp_path) as board:
        async with motiond(tmp_path, rig_toml(board.path), name="first") as served:
            await wait_configured(board)
            sender = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
            await sender.stream(["G21 G90", "M3 S800", "G1 X100 F600"])  # a 10 s cut
            await asyncio.sleep(1.5)
            killed_ns = time.monotonic_ns()
            served.process.kill()
            await served.process.wait()
        await asyncio.sleep(MAX_DURATION_S + LEAD_S + 0.5)
        gpio = board.gpio()
        duties = gpio.pwm_pb4()
        on = next(cycle for cycle, duty in duties if duty == 204)
        off = next(cycle for cycle, duty in duties if cycle > on and duty == 0)
        late_s = (gpio.host_ns(off) - killed_ns) / 1e9
        assert late_s <= MAX_DURATION_S + LEAD_S + 0.15, f"laser on {late_s:.3f} s after"
        last_step = max(c for c, v in gpio.edges.get("A0", []) if v == 1)
        assert last_step <= off, "the board stopped stepping too"
        async with motiond(tmp_path, rig_toml(board.path), name="second") as served:
            await wait_configured(board, times=2)  # restarted, then configured afresh
            start = board.gpio().ocr0[-1][0]
            client = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
            result = await client.stream(["G21 G91", "G1 X5 F3000"])
            assert result.replies == ["ok", "ok"]
            report = await until_idle(client)
            await asyncio.sleep(0.1)
            assert "MPos:5.000," in report
            assert x_steps(board.gpio(), start) == (400, 400)
            await client.close()


def axis_steps(gpio: GpioLog, step: str, direction: str, inverted: bool) -> tuple[int, int]:
    rises = [c for c, v in gpio.edges.get(step, []) if v == 1]
    net = sum(1 if gpio.level_at(direction, c) != inverted else -1 for c in rises)
    return len(rises), net


async def test_a_job_s_pins_make_exactly_the_commanded_steps_and_idle_follows_the_last_edge(
    tmp_path: Path
) -> None:
    async with klipper_rig(tmp_path) as board, motiond(tmp_path, rig_toml(board.path)) as served:
        await wait_configured(board)
        client = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        lines = ["G21 G90", "G1 X20 Y10 F6000", "G1 X5 Y25", "G1 X12.5 Y3 F3000"]
        assert (await client.stream(lines)).replies == ["ok"] * 4
        reports: list[tuple[int, str]] = []
        while not reports or not reports[-1][1].startswith("<Idle"):
            report = await status(client)
            reports.append((time.monotonic_ns(), report))
            await asyncio.sleep(0.01)
        idle_ns, idle_report = reports[-1]
        assert any(r.startswith("<Run") for _, r in reports)
        assert "MPos:12.500,3.000|" in idle_report
        await asyncio.sleep(0.3)  # the log is written every 10 ms of simulated time
        gpio = board.gpio()
        assert axis_steps(gpio, "A0", "A1", inverted=True) == (1600 + 1200 + 600, 1000)
        assert axis_steps(gpio, "A3", "A4", inverted=False) == (800 + 1200 + 1760, 240)
        last_edge = max(c for pin in ("A0", "A3") for c, v in gpio.edges[pin] if v == 1)
        assert gpio.host_ns(last_edge) <= idle_ns, "Idle only after the last step edge"
        await client.close()


async def test_a_board_that_dies_mid_job_is_an_alarm_in_one_log_line(tmp_path: Path) -> None:
    async with klipper_rig(tmp_path) as board, motiond(tmp_path, rig_toml(board.path)) as served:
        await wait_configured(board)
        client = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        await client.stream(["G21 G90", "M3 S800", "G1 X100 F3000"])
        await asyncio.sleep(0.5)
        board.process.kill()
        await board.process.wait()
        deadline = time.monotonic() + 2.0
        while not (report := await status(client)).startswith("<Alarm"):
            assert time.monotonic() < deadline, report
            await asyncio.sleep(0.02)
        await client.close()
    log = (tmp_path / "machine.log").read_text()
    assert "ALARM:42" in log and "Traceback" not in log, log


async def test_m400_sent_while_the_board_still_runs_the_move_answers_after_its_last_step(
    tmp_path: Path
) -> None:
    """``M400`` sent once motiond has generated a move's steps, while the board (a lead
    behind) still makes them: its ``ok`` comes after the board's last step edge."""
    async with klipper_rig(tmp_path) as board, motiond(tmp_path, rig_toml(board.path)) as served:
        await wait_configured(board)
        client = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
        assert (await client.stream(["G21 G90", "G1 X10 F6000"])).replies == ["ok"] * 2
        await asyncio.sleep(0.25)  # the steps generated; the board, LEAD_S behind, still moves
        assert (await client.stream(["M400"])).replies == ["ok"] * 3
        ok_ns = time.monotonic_ns()
        await asyncio.sleep(0.3)  # the log is written every 10 ms of simulated time
        gpio = board.gpio()
        assert x_steps(gpio) == (800, 800)
        last_edge = max(c for c, v in gpio.edges["A0"] if v == 1)
        assert gpio.host_ns(last_edge) <= ok_ns, "M400 answered before the board's last step"
        await client.close()
