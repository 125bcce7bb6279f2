"""The laser and air assist through the real Moonraker, as Klipper's output pins: the laser's
duty as it is now (read-only), air assist switched with ``SET_PIN`` (its M8/M9 in order)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.e2e.test_moonraker import ENDSTOPS, stack
from tests.support.moonraker import MoonrakerError

LASER_AND_AIR = ENDSTOPS + """
[laser]
maximum_s_value = 1000
[switch.air]
on_mcode = 8
off_mcode = 9
"""


async def test_laser_power_and_air_assist_are_output_pins(tmp_path: Path) -> None:
    async with stack(tmp_path, LASER_AND_AIR) as (_, server, _socket):
        names = (await server.get("/printer/objects/list"))["objects"]
        assert {"output_pin laser", "output_pin air"} <= set(names)
        settings = (await server.query(configfile=["settings"]))["configfile"]["settings"]
        assert settings["output_pin air"]["pwm"] is False  # a toggle: on or off
        await server.gcode("$X\nG1 X100 F1200 M3 S500")  # 5 s at 20 mm/s, half power
        status = await server.wait_for(lambda s: s["output_pin laser"]["value"] > 0,
                                       **{"output_pin laser": None})
        assert status["output_pin laser"]["value"] == pytest.approx(0.5)
        await server.gcode("M5")
        with pytest.raises(MoonrakerError) as refused:
            await server.gcode("SET_PIN PIN=laser VALUE=1")
        assert "read-only" in refused.value.body["error"]["message"]
        await server.gcode("SET_PIN PIN=air VALUE=1")  # Mainsail's toggle
        await server.wait_for(lambda s: s["output_pin air"]["value"] == 1.0,
                              **{"output_pin air": None})
        await server.gcode("M9")
        await server.wait_for(lambda s: s["output_pin air"]["value"] == 0.0,
                              **{"output_pin air": None})
