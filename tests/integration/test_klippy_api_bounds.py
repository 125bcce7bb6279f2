"""[klippy_api]'s bounds over its real socket, motiond in this process: the connection cap
answers the next client why it is refused, waiting scripts share a byte budget that comes back
when their client goes, and a long script, though translated in pieces, still stops on an
M112 at arrival and runs nothing when one of its lines is malformed."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

from modules.klippy_api.module import MAX_CONNECTIONS, SCRIPT_BYTES
from server.runtime.events import MachineState
from tests.integration.test_klippy_api_socket import served
from tests.support.klippy_client import KlippyClient, klippy_client

MIB = 1 << 20
COMMENT = "; a comment of a long script\n"
COMMENTS = COMMENT * ((MIB - 256) // (len(COMMENT) + 1))  # ~1 MiB as JSON


async def test_a_client_beyond_the_cap_is_told_why_and_the_others_are_served(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (_, socket), contextlib.AsyncExitStack() as stack:
        clients = [await stack.enter_async_context(klippy_client(socket))
                   for _ in range(MAX_CONNECTIONS)]
        for api in clients:
            assert (await api.call("info"))["result"]["state"] == "ready"
        async with klippy_client(socket) as late:
            refused = await late.call("info")
            assert refused["id"] == 1 and "too many API connections" in str(refused["error"])
        assert (await clients[-1].call("info"))["result"]["state"] == "ready"
    async with served(tmp_path) as (_, socket), klippy_client(socket) as api:
        assert "result" in await api.call("info")  # a slot comes back when a client goes


async def test_scripts_beyond_the_byte_budget_are_refused_and_come_back_when_the_client_goes(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket):
        budget = app.kernel.modules["klippy_api"].script_bytes  # type: ignore[attr-defined]
        fits = SCRIPT_BYTES // len(COMMENTS)
        async with klippy_client(socket) as greedy:
            ids = [await greedy.send("gcode/script", script=COMMENTS) for _ in range(fits + 1)]
            refused = await greedy.answer(ids[-1])
            assert "waiting hold" in refused["error"]["message"], refused
            assert budget.used_bytes > (fits - 1) * len(COMMENTS)
        for _ in range(100):
            if budget.used_bytes == 0:
                break
            await asyncio.sleep(0.02)
        assert budget.used_bytes == 0, "the scripts of a client that went were dropped"
        async with klippy_client(socket) as next_client:
            taken = await next_client.send("gcode/script", script=COMMENTS)
            await next_client.call("info")
            assert taken not in next_client.answers, "queued, not refused"


async def moving(app: object, api: KlippyClient) -> None:
    await api.send("gcode/script", script="G1 X300 F3000")
    for _ in range(200):
        if app.kernel.machine.stepgen.state.speed_mm_s > 0:  # type: ignore[attr-defined]
            return
        await asyncio.sleep(0.01)
    raise TimeoutError("the machine did not move")


async def test_an_m112_at_the_end_of_a_long_script_stops_the_machine_on_arrival(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), klippy_client(socket) as api:
        await moving(app, api)
        await api.send("gcode/script", script=COMMENT * 10_000 + "M112\n")
        for _ in range(50):
            if app.kernel.state is MachineState.ALARM:
                break
            await asyncio.sleep(0.01)
        assert app.kernel.alarm_code == 40, "acted within 0.5 s, ahead of the moving script"
        assert app.kernel.machine.stepgen.state.position_mm[0] < 300


async def test_a_long_script_with_a_malformed_last_line_runs_none_of_its_lines(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), klippy_client(socket) as api:
        lines = "".join(f"G1 X{1 + i % 50} F30000\n" for i in range(5000))
        answer = await api.call("gcode/script", script=lines + "SAVE_GCODE_STATE NAME=x\n")
        assert "SAVE_GCODE_STATE" in answer["error"]["message"]
        assert app.kernel.machine.stepgen.state.position_mm[0] == 0.0
        assert (await api.call("gcode/script", script="G1 X5 F30000"))["result"] == {}
