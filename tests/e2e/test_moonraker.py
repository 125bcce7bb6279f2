"""``[klippy_api]`` against the real Moonraker: motiond as the Klipper behind it.

Moonraker (PyPI, its own environment: :mod:`tests.support.moonraker`) connects to motiond's API
socket and serves its HTTP API; every assertion reads what motiond executed (its status report
over TCP, or the printer objects through Moonraker).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import stat
from collections.abc import AsyncIterator
from pathlib import Path

import aiohttp
import pytest

from tests.e2e.test_mqtt import mpos, tcp_report
from tests.support.moonraker import Moonraker, MoonrakerError, documented_config, moonraker
from tests.support.processes import Served, motiond

# An XY laser with homing switches below zero, and Z without one.
AXES = "".join(
    f"[axes.{axis}]\nsteps_per_mm = 80\nmax_rate_mm_s = 200\naccel_mm_s2 = 2000\n"
    f"min_mm = 0\nmax_mm = 300\n" for axis in "xy"
) + ("[axes.z]\nsteps_per_mm = 400\nmax_rate_mm_s = 10\naccel_mm_s2 = 200\n"
     "min_mm = -50\nmax_mm = 0\n")
ENDSTOPS = """
[endstops]
axes.x = { direction = "min", seek_mm_s = 200, feed_mm_s = 20, pull_off_mm = 1, switch_at_mm = -1 }
axes.y = { direction = "min", seek_mm_s = 200, feed_mm_s = 20, pull_off_mm = 1, switch_at_mm = -1 }
"""


@contextlib.asynccontextmanager
async def stack(tmp_path: Path, machine_toml: str = ENDSTOPS, axes_toml: str = AXES,
                ) -> AsyncIterator[tuple[Served, Moonraker, Path]]:
    """motiond and Moonraker configured as docs/moonraker.md says, word for word (the port
    aside), for a user whose home is ``tmp_path/home``: no link between their folders."""
    home = tmp_path / "home"
    motiond_toml, moonraker_conf, options = documented_config(home)
    printer_data = home / "printer_data"
    async with contextlib.AsyncExitStack() as stack:
        served = await stack.enter_async_context(motiond(
            tmp_path, machine_toml + motiond_toml, axes_toml=axes_toml, home=home,
            args=options))
        served = dataclasses.replace(served, jobs=printer_data / "gcodes")
        socket = printer_data / "comms" / "klippy.sock"
        server = await stack.enter_async_context(
            moonraker(tmp_path, socket, conf=moonraker_conf, home=home))
        yield served, server, socket


async def test_moonraker_sees_motiond_ready_scripts_home_jog_move_and_emergency_stop(
        tmp_path: Path) -> None:
    async with stack(tmp_path) as (served, server, socket):
        await _ready_with_position(served, server, socket)
        await _console_output_reaches_the_gcode_store(server)
        await _klipper_words_for_unknown_commands_and_velocity_limits(server)
        await _home_jog_and_move(served, server)
        await _emergency_stop_then_firmware_restart(served, server)


async def _ready_with_position(served: Served, server: Moonraker, socket: Path) -> None:
    assert stat.S_IMODE(socket.stat().st_mode) == 0o600
    info = await server.get("/printer/info")
    assert info["state"] == "ready"
    assert "motiond" in info["software_version"]
    objects = (await server.get("/printer/objects/list"))["objects"]
    assert {"toolhead", "print_stats", "virtual_sdcard", "webhooks"} <= set(objects)
    assert not [name for name in objects if name.startswith(("extruder", "heater"))]
    status = await server.query(toolhead=["position", "homed_axes"],
                                configfile=["settings"])
    assert status["toolhead"]["position"] == [0.0, 0.0, 0.0, 0.0]
    assert status["toolhead"]["homed_axes"] == "z"  # X and Y have switches, not yet homed
    sdcard = status["configfile"]["settings"]["virtual_sdcard"]["path"]
    assert Path(sdcard) == served.jobs_dir.resolve()
    assert (await server.get("/server/info"))["warnings"] == []  # none, on this set-up
    assert {"gcode_macro PAUSE", "gcode_macro RESUME", "gcode_macro CANCEL_PRINT"} <= set(objects)
    async with server.session.get(server.url + "/server/files/klippy.log") as log:
        assert log.status == 200  # the "Klipper log" buttons: motiond's --log-file


async def _home_jog_and_move(served: Served, server: Moonraker) -> None:
    await server.gcode("G28")
    status = await server.wait_for(lambda s: s["toolhead"]["homed_axes"] == "xyz",
                                   toolhead=["homed_axes"])
    assert status["toolhead"]["homed_axes"] == "xyz"
    await server.gcode("G1 X20 Y10 F6000")
    await server.wait_for(lambda s: s["motion_report"]["live_position"][:2] == [20.0, 10.0],
                          motion_report=["live_position"])
    assert mpos(await tcp_report(served.tcp_port))[:2] == [20.0, 10.0]
    await server.gcode("_CLIENT_LINEAR_MOVE X=-5 F=3000")  # Mainsail's jog
    await server.wait_for(lambda s: s["toolhead"]["position"][0] == 15.0,
                          toolhead=["position"])
    await server.gcode("SAVE_GCODE_STATE NAME=_ui_movement\nG91\nG1 Y5 F3000\n"
                       "RESTORE_GCODE_STATE NAME=_ui_movement")
    status = await server.wait_for(lambda s: s["toolhead"]["position"][1] == 15.0,
                                   toolhead=["position"], gcode_move=None)
    assert status["gcode_move"]["absolute_coordinates"] is True  # the jog left G90 alone
    await server.gcode("M220 S150")
    status = await server.query(gcode_move=["speed_factor"])
    assert status["gcode_move"]["speed_factor"] == 1.5
    with pytest.raises(MoonrakerError) as refused:
        await server.gcode("G1 X500")  # beyond the travel
    assert "error:" in str(refused.value.body)
    hooks = (await server.query(webhooks=None))["webhooks"]  # ALARM:2, and no shutdown
    assert hooks["state"] == "ready" and "ALARM:2" in hooks["state_message"]
    await server.gcode("$X")


async def test_store_through_moonraker_then_print_pause_resume_and_cancel(tmp_path: Path) -> None:
    async with stack(tmp_path) as (served, server, _):
        await server.gcode("G28")
        job = "G90 G21\nM4 S500\n" + "".join(
            f"G1 X{10 + i % 2 * 20} Y{10 + i} F6000\n" for i in range(30)) + "M5\n"
        form = aiohttp.FormData()
        form.add_field("file", job.encode(), filename="square.gcode")
        async with server.session.post(server.url + "/server/files/upload", data=form) as reply:
            assert reply.status == 201, await reply.text()
        assert (served.jobs_dir / "square.gcode").read_text() == job
        async with server.session.ws_connect(server.url + "/websocket") as front_end:
            await front_end.send_json({"jsonrpc": "2.0", "id": 1,
                                       "method": "printer.objects.subscribe",
                                       "params": {"objects": {"print_stats": ["state"]}}})
            async for message in front_end:  # the subscription stands before the print
                if message.json().get("id") == 1:
                    break
            states = asyncio.create_task(_print_states(front_end))
            await server.post("/printer/print/start", {"filename": "square.gcode"})
            status = await server.wait_for(lambda s: s["virtual_sdcard"]["progress"] > 0,
                                           virtual_sdcard=None, print_stats=None)
            assert status["print_stats"]["state"] == "printing"
            assert status["virtual_sdcard"]["file_size"] == len(job)
            await server.post("/printer/print/pause")
            await server.wait_for(lambda s: s["print_stats"]["state"] == "paused"
                                  and s["pause_resume"]["is_paused"], print_stats=None,
                                  pause_resume=None)
            assert (await tcp_report(served.tcp_port)).startswith("<Hold")
            await server.post("/printer/print/resume")
            await server.wait_for(lambda s: s["print_stats"]["state"] == "printing",
                                  print_stats=None)
            await server.post("/printer/print/cancel")
            await server.wait_for(lambda s: s["print_stats"]["state"] == "cancelled",
                                  print_stats=None)
            await asyncio.sleep(0.5)  # a person's pace: a start 0.1 s after a cancel can
            await _history_shows(server, ["cancelled"])  # confuse Moonraker's history
            await server.post("/printer/print/start", {"filename": "square.gcode"})
            status = await server.wait_for(lambda s: s["print_stats"]["state"] == "complete",
                                           timeout_s=60, print_stats=None, virtual_sdcard=None)
            assert status["virtual_sdcard"]["progress"] == 1.0
            await asyncio.sleep(0.6)  # the last push
            states.cancel()
            pushed = await states
        assert pushed == ["printing", "paused", "printing", "cancelled", "printing", "complete"]
        await _history_shows(server, ["completed", "cancelled"])
        await server.post("/printer/restart")  # Klipper's restart: the job is forgotten
        await _klippy_ready(server)
        status = await server.query(print_stats=["state", "filename"])
        assert status["print_stats"] == {"state": "standby", "filename": ""}


async def _history_shows(server: Moonraker, statuses: list[str]) -> None:
    """Moonraker's job history lists ``statuses``, newest first (it follows print_stats)."""
    for _ in range(300):
        history = await server.get("/server/history/list")
        if [job["status"] for job in history["jobs"]] == statuses:
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"history {history['jobs']}")



async def _print_states(front_end: aiohttp.ClientWebSocketResponse) -> list[str]:
    """The ``print_stats.state`` values a front-end is pushed, in order, until cancelled."""
    states: list[str] = []
    with contextlib.suppress(asyncio.CancelledError):
        async for message in front_end:
            data = message.json()
            if data.get("method") == "notify_status_update":
                state = data["params"][0].get("print_stats", {}).get("state")
                if state is not None:
                    states.append(state)
    return states


async def _emergency_stop_then_firmware_restart(served: Served, server: Moonraker) -> None:
    moving = asyncio.create_task(server.gcode("G1 X250 Y250 F600"))
    await server.wait_for(lambda s: s["motion_report"]["live_velocity"] > 0,
                          motion_report=None)
    await server.post("/printer/emergency_stop")
    status = await server.wait_for(lambda s: s["webhooks"]["state"] == "shutdown",
                                   timeout_s=5, webhooks=None)
    assert "ALARM:40" in status["webhooks"]["state_message"]
    homed = await server.query(toolhead=["homed_axes"])
    assert homed["toolhead"]["homed_axes"] == "z", "an emergency stop loses X and Y's homing"
    with contextlib.suppress(MoonrakerError):
        await moving
    stopped_at = mpos(await tcp_report(served.tcp_port))
    await asyncio.sleep(0.3)
    assert mpos(await tcp_report(served.tcp_port)) == stopped_at
    assert stopped_at[0] < 250
    with pytest.raises(MoonrakerError):
        await server.gcode("G1 X10")  # locked out
    await server.post("/printer/firmware_restart")
    await _klippy_ready(server)
    await server.gcode("G1 X10 F6000")
    await server.wait_for(lambda s: s["toolhead"]["position"][0] == 10.0,
                          toolhead=["position"])
    for lose in ("M84", "RESTART"):  # motors off, and Klipper's restart, unhome as Klipper's
        await server.gcode("G28")
        await server.wait_for(lambda s: s["toolhead"]["homed_axes"] == "xyz",
                              toolhead=["homed_axes"])
        with contextlib.suppress(MoonrakerError):  # RESTART: the connection closes
            await server.gcode(lose)
        await _klippy_ready(server)
        await server.wait_for(lambda s: s["toolhead"]["homed_axes"] == "z",
                              toolhead=["homed_axes"])


async def _klippy_ready(server: Moonraker) -> None:
    """Until Moonraker is connected to motiond again (after a restart), ready."""
    await asyncio.sleep(0.3)  # Moonraker sees the connection close first
    for _ in range(200):
        with contextlib.suppress(MoonrakerError, AssertionError):
            info = await server.get("/server/info")
            if info["klippy_state"] == "ready":
                return
        await asyncio.sleep(0.1)
    raise AssertionError("Moonraker did not reconnect")


async def _console_output_reaches_the_gcode_store(server: Moonraker) -> None:
    await server.gcode("M114")
    await server.gcode("M117 Cutting plywood")
    status = await server.query(display_status=None)
    assert status["display_status"]["message"] == "Cutting plywood"
    store = await server.get("/server/gcode_store", count="50")
    responses = [item["message"] for item in store["gcode_store"]
                 if item["type"] == "response"]
    assert any(message.startswith("X:0.0000 Y:0.0000") for message in responses), responses


async def _klipper_words_for_unknown_commands_and_velocity_limits(server: Moonraker) -> None:
    with pytest.raises(MoonrakerError) as unknown:
        await server.gcode("FOO_BAR")
    assert 'Unknown command:"FOO_BAR"' in unknown.value.body["error"]["message"]
    with pytest.raises(MoonrakerError) as limit:
        await server.gcode("SET_VELOCITY_LIMIT VELOCITY=100")  # Mainsail's Machine panel
    message = limit.value.body["error"]["message"]
    assert "Error on 'SET_VELOCITY_LIMIT VELOCITY=100'" in message and "max_rate_mm_s" in message
    await server.gcode("SET_VELOCITY_LIMIT")
    store = await server.get("/server/gcode_store", count="10")
    responses = [item["message"] for item in store["gcode_store"]]
    assert "// max_velocity: 200.000000" in "\n".join(responses), responses
