"""A job through the real Moonraker as a Klipper user runs it: a jog in a pause answers at
once, the time left the front-ends compute (print time / progress - print time, as
Mainsail's and Fluidd's "file" estimate) is motiond's planned time, not the file position's,
and the Z-offset buttons baby-step a running job."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import aiohttp
import pytest

from tests.e2e.test_moonraker import stack
from tests.e2e.test_mqtt import mpos, tcp_report
from tests.support.moonraker import Moonraker, MoonrakerError

# Most lines first, most time last: the file position says 98 % where the time says 10 %.
JOB = ("G90 G21\nG1 X0 Y0 F6000\n"
       + "".join(f"G1 X{(i % 2) * 0.5:g} Y{i * 0.25:g}\n" for i in range(200))
       + "G1 X100 F3000\nG1 X0\nG1 X100\n")


# Z down to the focus, a row of cuts there (about 1.5 s), then up to Z-1 at the origin.
FOCUSED = ("G90 G21\nG1 Z-2 F600\n" + "".join(f"G1 X{i} Y5 F1500\n" for i in range(1, 31))
           + "G1 X0 Y0 Z-1\n")


async def _upload_and_start(server: Moonraker, name: str, text: str) -> None:
    form = aiohttp.FormData()
    form.add_field("file", text.encode(), filename=name)
    async with server.session.post(server.url + "/server/files/upload", data=form) as reply:
        assert reply.status == 201, await reply.text()
    await server.post("/printer/print/start", {"filename": name})


async def test_jog_in_a_pause_answers_at_once_and_time_left_is_motiond_s(
        tmp_path: Path) -> None:
    async with stack(tmp_path) as (_, server, _socket):
        await server.gcode("G28")
        await _upload_and_start(server, "raster.gcode", JOB)
        await server.wait_for(lambda s: s["print_stats"]["state"] == "printing",
                              print_stats=None)
        await server.post("/printer/print/pause")
        await server.wait_for(lambda s: s["print_stats"]["state"] == "paused",
                              print_stats=None)
        asked_s = time.monotonic()
        with pytest.raises(MoonrakerError) as refused:
            await server.gcode("_CLIENT_LINEAR_MOVE X=5 F=3000")  # Mainsail's jog button
        assert time.monotonic() - asked_s < 2.0, "answered at once, not at Resume"
        assert "paused" in refused.value.body["error"]["message"]
        with pytest.raises(MoonrakerError):  # any console line: it would wait for Resume
            await asyncio.wait_for(server.gcode("M114"), 2.0)
        await server.post("/printer/print/resume")
        left_s, at_s = await _time_left_at(server, 0.2)
        await server.wait_for(lambda s: s["print_stats"]["state"] == "complete",
                              timeout_s=60, print_stats=None)
        real_s = time.monotonic() - at_s
        assert left_s == pytest.approx(real_s, rel=0.05), (left_s, real_s)


async def _time_left_at(server: Moonraker, fraction: float) -> tuple[float, float]:
    """The front-ends' time left once the job is ``fraction`` done, and when (monotonic)."""
    while True:
        status = await server.query(print_stats=["print_duration"],
                                    virtual_sdcard=["progress"])
        progress = status["virtual_sdcard"]["progress"]
        if progress >= fraction:
            printed_s = status["print_stats"]["print_duration"]
            return printed_s / progress - printed_s, time.monotonic()
        await asyncio.sleep(0.05)


async def test_the_z_offset_buttons_baby_step_a_running_job(tmp_path: Path) -> None:
    async with stack(tmp_path) as (served, server, _socket):
        await server.gcode("G28")
        await _upload_and_start(server, "focused.gcode", FOCUSED)
        await server.wait_for(lambda s: s["print_stats"]["state"] == "printing",
                              print_stats=None)
        await server.gcode("SET_GCODE_OFFSET Z_ADJUST=-0.05 MOVE=1")  # Mainsail's button
        status = await server.query(print_stats=["state"], gcode_move=["homing_origin"])
        assert status["print_stats"]["state"] == "printing", "applied while the job runs"
        assert status["gcode_move"]["homing_origin"][2] == -0.05
        await server.wait_for(lambda s: s["print_stats"]["state"] == "complete",
                              timeout_s=15, print_stats=None)
        where = mpos(await tcp_report(served.tcp_port))
        status = await server.query(gcode_move=["homing_origin", "gcode_position"])
    assert where == [0.0, 0.0, -1.05], "the job's later moves went 0.05 mm lower"
    assert status["gcode_move"]["homing_origin"][2] == -0.05, "the offset stays after the job"
    assert status["gcode_move"]["gcode_position"][2] == -1.0
