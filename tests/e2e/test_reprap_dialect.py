"""The RepRap dialect as Marlin hosts (OctoPrint, Repetier, Pronterface) rely on it, over a real
TCP socket and a real pty: framed lines, Marlin's replies, the busy keep-alive, M400, M410."""

from __future__ import annotations

import asyncio
import contextlib
import grp
import os
import stat
import time
from collections.abc import AsyncIterator
from functools import reduce
from operator import xor
from pathlib import Path

import pytest

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport
from tests.conftest import make_config
from tests.e2e.test_streams import PtyClient, TcpClient
from tests.support.senders import wait_for

LASER = {"minimum_power": 0.1, "maximum_power": 0.8, "maximum_s_value": 1000}


class Host(TcpClient):
    """A RepRap host: numbered, checksummed lines; replies read up to their ``ok``."""

    number = 0

    async def framed(self, text: str, timeout_s: float = 5.0) -> list[str]:
        self.number += 1
        await self.send(frame(self.number, text))
        return await self.until_ok(timeout_s)

    async def until_ok(self, timeout_s: float = 5.0) -> list[str]:
        got: list[str] = []
        while True:
            line = await self.line(timeout_s)
            if line:
                got.append(line)
            if line.startswith("ok"):
                return got


def gid_of(group: str) -> int:
    """The group's id; for "", the group this system gives a new pseudo-terminal."""
    if group:
        return grp.getgrnam(group).gr_gid
    master, slave = os.openpty()
    try:
        return os.fstat(slave).st_gid
    finally:
        os.close(master)
        os.close(slave)


def frame(number: int, text: str) -> bytes:
    head = f"N{number} {text}"
    return f"{head}*{reduce(xor, head.encode(), 0)}\n".encode()


@contextlib.asynccontextmanager
async def serving(**sections: object) -> AsyncIterator[tuple[App, Host]]:
    app = App(make_config(**sections), clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await asyncio.wait_for(app.ready.wait(), 5)
    host = Host(*await asyncio.open_connection("127.0.0.1", app.transports[0].port))
    try:
        await host.send(b"N0 M110 N0*125\n")  # OctoPrint's first line
        assert "ok" in await host.lines_until("ok")
        yield app, host
    finally:
        with contextlib.suppress(OSError):
            await host.close()
        app.request_stop()
        await asyncio.wait_for(task, 5)


async def test_a_locked_machine_answers_a_hosts_connect_queries_and_unlocks() -> None:
    async with serving() as (app, host):
        await host.framed("M112")
        assert app.kernel.state is MachineState.ALARM
        m115 = await host.framed("M115")
        m21 = await host.framed("M21")
        m105 = await host.framed("M105")
        m114 = await host.framed("M114")
        m400 = await host.framed("M400")
        move = await host.framed("G0 X10")
        unlock = await host.framed("$X")
        state = app.kernel.state
    assert m115[0].startswith("FIRMWARE_NAME:motiond") and "Cap:EMERGENCY_PARSER:1" in m115
    assert m21[0].startswith("echo:Unknown command") and m21[1:] == ["ok"], m21
    assert m105 == ["ok T:0.0 /0.0 B:0.0 /0.0"]
    assert m114[0].startswith("C: X:0.0000 Y:0.0000 Z:0.0000 E:0.0000") and m114[-1] == "ok"
    assert m400 == ["ok"]
    # an effect stays locked out, answered so that OctoPrint keeps the connection and shows why
    assert move[0].startswith("//action:notification ") and "ALARM:40" in move[0], move
    assert move[1].startswith("echo:") and "M999" in move[1] and "(code 9)" in move[1]
    assert move[2:] == ["ok"] and not any(line.startswith("Error:") for line in move)
    assert unlock[-1] == "ok" and state is MachineState.IDLE


async def test_an_out_of_range_line_is_an_echo_for_that_line_and_no_alarm() -> None:
    async with serving() as (app, host):
        refused = await host.framed("G0 X500")
        state = app.kernel.state
        moved = await host.framed("G0 X10")
        await host.framed("M400")
        position = app.kernel.machine.stepgen.state.position_mm
    assert refused[0].startswith("echo:") and "(code 40)" in refused[0] and refused[1:] == ["ok"]
    assert not any(line.startswith(("Error:", "ALARM")) for line in refused)
    assert state is MachineState.IDLE and moved == ["ok"] and position[0] == pytest.approx(10)


async def test_grbl_senders_still_get_m105_as_a_line_before_ok_and_the_soft_limit_alarm() -> None:
    app = App(make_config(), clock=RealClock(), transports=[TcpTransport])
    task = asyncio.create_task(app.run())
    await asyncio.wait_for(app.ready.wait(), 5)
    client = TcpClient(*await asyncio.open_connection("127.0.0.1", app.transports[0].port))
    try:
        await client.lines_until("Grbl 1.1h ['$' for help]")
        assert await client.reply("G21") == ["ok"]
        assert await client.reply("M105") == ["T:0.0 /0.0 B:0.0 /0.0", "ok"]
        await client.send(b"G0 X500\n")
        refused = await client.lines_until("ALARM:2")  # as Grbl: the alarm is the line's reply
        state = app.kernel.state
    finally:
        await client.close()
        app.request_stop()
        await asyncio.wait_for(task, 5)
    assert not [line for line in refused if line.startswith(("error:", "ok"))], refused
    assert state is MachineState.ALARM


async def test_m400_holds_its_ok_until_motion_ends_with_busy_every_two_seconds() -> None:
    async with serving() as (app, host):
        assert await host.framed("G1 X70 F1000") == ["ok"]  # 4.2 s
        started_s = time.monotonic()
        waited = await host.framed("M400", timeout_s=15)
        held_s = time.monotonic() - started_s
        idle = app.kernel.machine.stepgen.idle
        position = app.kernel.machine.stepgen.state.position_mm
    assert waited[-1] == "ok" and idle and position[0] == pytest.approx(70)
    busy = [line for line in waited if line == "echo:busy: processing"]
    assert waited[:-1] == busy and len(busy) >= 1, waited
    assert len(busy) <= held_s / 2.0 + 0.5, "one every 2 s"


async def test_m410_stops_at_once_turns_the_laser_off_and_answers_the_flushed_line() -> None:
    async with serving(laser=LASER) as (app, host):
        assert await host.framed("M3 S300") == ["ok"]
        assert await host.framed("G1 X100 F600") == ["ok"]  # 10 s
        await asyncio.sleep(1.0)
        laser = app.kernel.modules["laser"]
        firing = laser.power  # type: ignore[attr-defined]
        host.number += 1
        await host.send(frame(host.number, "G1 X0 Y0"))  # waits for no room: it is queued
        await host.send(frame(host.number + 1, "M410"))
        host.number += 1
        started_s = time.monotonic()
        await wait_for(lambda: app.kernel.machine.stepgen.idle, 2.0, "the quickstop")
        stopped_s = time.monotonic() - started_s
        power = laser.power  # type: ignore[attr-defined]
        replies = await host.until_ok()
        replies += await host.until_ok()
        modal = await host.framed("$G")
        await asyncio.sleep(0.3)
        position = app.kernel.machine.stepgen.state.position_mm
    assert firing > 0 and power == 0.0 and stopped_s < 1.0
    assert 5 < position[0] < 95 and position[1] == 0, "stopped where it was, X0 Y0 never ran"
    # the queued move is answered once, as not run (flushed, or refused while it waited)
    assert replies[0].startswith("echo:") and "(code 45)" in replies[0], replies
    assert replies[1:] == ["ok", "ok"], "one ok for the move, one for M410"
    assert any("M5" in line for line in modal), modal


async def test_m117_and_m118_take_text() -> None:
    async with serving() as (app, host):
        display = await host.framed("M117 Done! 100%")
        echo = await host.framed("M118 E1 hello world")
    assert display == ["[MSG:Done! 100%]", "ok"]
    assert echo == ["echo:hello world", "ok"]


@pytest.mark.parametrize(("sections", "mode", "group"), [
    ({}, 0o660, "dialout"),
    ({"pty_group": "root", "pty_mode": 0o600}, 0o600, "root"),
    ({"pty_group": ""}, 0o660, ""),  # "": the group a new pseudo-terminal gets
])
async def test_the_pty_is_shared_with_its_group_as_a_serial_port(
    tmp_path: Path, sections: dict[str, object], mode: int, group: str
) -> None:
    link = tmp_path / "ttyMotiond"
    config = make_config(serial={"pty": str(link), **sections})
    app = App(config, clock=RealClock(), transports=[SerialTransport])
    task = asyncio.create_task(app.run())
    await asyncio.wait_for(app.ready.wait(), 5)
    try:
        info = os.stat(link)
        client = PtyClient(link)
        await client.send(b"M105\n")
        answer = await client.lines_until("ok T:0.0 /0.0 B:0.0 /0.0")
        await client.close()
    finally:
        app.request_stop()
        await asyncio.wait_for(task, 5)
    assert stat.S_IMODE(info.st_mode) == mode and info.st_gid == gid_of(group)
    assert answer[-1] == "ok T:0.0 /0.0 B:0.0 /0.0"


async def test_m113_sets_the_connections_busy_interval_and_zero_stops_it() -> None:
    async with serving() as (app, host):
        assert await host.framed("M113 S0") == ["ok"]
        assert await host.framed("M113") == ["echo:M113 S0", "ok"]
        assert await host.framed("G1 X40 F1000") == ["ok"]  # 2.4 s
        quiet = await host.framed("M400", timeout_s=10)
        assert await host.framed("M113 S1") == ["ok"]
        assert await host.framed("G1 X0") == ["ok"]
        busy = await host.framed("M400", timeout_s=10)
        refused = await host.framed("M113 S90")
    assert quiet == ["ok"]
    assert busy[:-1] == ["echo:busy: processing"] * len(busy[:-1]) and len(busy) >= 3, busy
    assert refused[0].startswith("echo:") and "(code 2)" in refused[0]
