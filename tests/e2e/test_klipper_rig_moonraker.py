"""The stock Klipper firmware (the klipper-avr rig) behind motiond behind the real Moonraker:
an emergency stop from the front-end shuts the board down, and FIRMWARE_RESTART, as a Klipper
user recovers, restarts it and the machine moves again."""

from __future__ import annotations

import asyncio
from pathlib import Path

from tests.e2e.test_klipper_rig import rig_toml
from tests.e2e.test_moonraker import _klippy_ready, stack
from tests.support.klipper_rig import klipper_rig, wait_configured
from tests.support.processes import AXES_TOML


async def test_firmware_restart_recovers_the_board_after_an_emergency_stop(
        tmp_path: Path) -> None:
    async with (klipper_rig(tmp_path) as board,
                stack(tmp_path, rig_toml(board.path), AXES_TOML) as (_, server, _socket)):
        await wait_configured(board)
        await server.gcode("G1 X100 F3000")  # 2 s
        await asyncio.sleep(1.0)
        await server.post("/printer/emergency_stop")
        status = await server.wait_for(lambda s: s["webhooks"]["state"] == "shutdown",
                                       timeout_s=5, webhooks=None)
        assert "FIRMWARE_RESTART" in status["webhooks"]["state_message"]
        await server.post("/printer/firmware_restart")
        await _klippy_ready(server)
        await wait_configured(board, times=2)  # restarted, then configured afresh
        assert (await server.query(webhooks=None))["webhooks"]["state"] == "ready"
        await server.gcode("G1 X10 F3000")
        await server.wait_for(lambda s: s["toolhead"]["position"][0] == 10.0,
                              timeout_s=10, toolhead=["position"])
