"""Stop means stop on Klipper's API socket too (issue #36): what Moonraker's front-ends ask
for (a stored job's start, a work offset with a move) never runs after a stop, and Klipper's
own stops (``emergency_stop``, ``FIRMWARE_RESTART``) leave the laser off in the modal state.

The laser machine of :mod:`tests.support.stop_rig` is served in this process with
``[klippy_api]``: the front-end speaks to its real Unix socket (JSON requests each ended by
0x03, as Moonraker sends them), Grbl senders and the operator to its real TCP port. What the
machine did is read from the simulated backend: its steps and its laser output.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from tests.support.stop_rig import (
    BANNER,
    STOP_AFTER_S,
    KlippyClient,
    LineClient,
    Rig,
    assert_a_reset_boards_modes,
    slow_to_check_job,
    stop_rig,
)


async def firmware_restart(api: KlippyClient) -> None:
    """``FIRMWARE_RESTART`` from the console: the server closes the API connection after it."""
    await api.send("gcode/script", script="FIRMWARE_RESTART")
    assert await api.closed_by_server(), "the front-end is made to reconnect"


# -- 1. SDCARD_PRINT_FILE whose start is still being checked -------------------------------------
@pytest.mark.parametrize("stop", ["ctrl-x-on-tcp", "emergency-stop-then-firmware-restart"])
async def test_a_print_whose_start_is_being_checked_never_starts_after_a_stop(
        tmp_path: Path, stop: str) -> None:
    async with stop_rig(tmp_path, klippy=True) as rig, rig.klippy() as api:
        rig.write_job("big.gcode", slow_to_check_job())
        operator = await rig.tcp()
        start = await api.send("gcode/script", script="SDCARD_PRINT_FILE FILENAME=big.gcode")
        await asyncio.sleep(STOP_AFTER_S)
        assert start not in api.answers, "the check ended before the stop: make the job bigger"
        stopped_s = time.monotonic()
        if stop == "ctrl-x-on-tcp":
            operator.send(b"\x18")
        else:
            assert await api.call("emergency_stop") == {"id": 2, "result": {}}
        answer = await api.answer(start)
        answered_s = time.monotonic() - stopped_s
        if stop != "ctrl-x-on-tcp":
            await firmware_restart(api)
        await rig.assert_still(1.5, "after the stop")  # the job's first moves: 0.1 s in
        report = await operator.report()
    assert "error" in answer, answer
    assert answered_s < 1.0, f"the stop ends the check: answered {answered_s:.2f} s after it"
    assert report.startswith("<Idle|"), report
    assert rig.app.kernel.jobs.progress() is None, "no job"


# -- 3. Klipper's stops leave the laser off in the modal state -----------------------------------
async def _emergency_stop_then_restart(rig: Rig, sender: LineClient) -> None:
    async with rig.klippy() as api:
        assert (await api.call("emergency_stop"))["result"] == {}
        await sender.until(lambda got: "ALARM:40" in got)
        await firmware_restart(api)


async def _restart_while_moving(rig: Rig, sender: LineClient) -> None:
    async with rig.klippy() as api:
        await api.send("gcode/firmware_restart")  # Moonraker's printer.firmware_restart
        assert await api.closed_by_server()
    assert "ALARM:3" in sender.lines, "a restart is a reset: the move was cut"


@pytest.mark.parametrize("stop", [_emergency_stop_then_restart, _restart_while_moving],
                         ids=["emergency-stop-then-firmware-restart", "firmware-restart"])
async def test_after_klippers_stops_the_modal_state_is_m5_s0_m9_and_the_next_move_is_dark(
        tmp_path: Path, stop: Callable[[Rig, LineClient], Awaitable[None]]) -> None:
    async with stop_rig(tmp_path, klippy=True) as rig:
        sender = await rig.tcp()
        assert await sender.command("G10 L20 P1 X-5 Y-3") == ["ok"]
        assert await sender.command("M3 S800") == ["ok"]
        assert await sender.command("G1 X30 F600") == ["ok"]
        await rig.moving()
        assert rig.laser_fired_since(0), "the move cut"
        await stop(rig, sender)
        assert (await sender.report()).startswith("<Idle|"), "unlocked by the restart"
        await assert_a_reset_boards_modes(rig, sender)


# -- 4. a deferred jog -------------------------------------------------------------------------
async def test_a_gcode_offset_move_waiting_for_anothers_motion_never_runs_after_a_reset(
        tmp_path: Path) -> None:
    async with stop_rig(tmp_path, klippy=True) as rig, rig.klippy() as api:
        sender, operator = await rig.tcp(), await rig.tcp()
        assert await sender.command("G1 X30 F600") == ["ok"]  # 3 s of motion
        await rig.moving()
        offset = await api.send("gcode/script", script="SET_GCODE_OFFSET Z_ADJUST=-5 MOVE=1")
        await asyncio.sleep(0.2)
        assert offset not in api.answers, "it waits for the sender's move"
        operator.send(b"!")
        await operator.wait_state("Hold:0")
        operator.send(b"\x18")
        await operator.until(lambda got: got.count(BANNER) == 2)
        answer = await api.answer(offset)
        await rig.assert_still(1.5, "after the reset")  # a 5 mm jog of Z takes about 1 s
        offsets = await operator.command("$#")
    assert "error" in answer, answer
    assert rig.backend.steps[2] == 0, "Z never moved"
    assert "[G92:0.000,0.000,0.000]" in offsets, "nor was the offset set"
