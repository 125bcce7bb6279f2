"""A real ``motiond`` process on the Klipper backend, streamed over TCP like any Grbl sender,
drives a virtual MCU on a pty; ``?`` and the job flow are those of every other backend."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from tests.support.processes import motiond
from tests.support.senders import CharCountingClient
from tests.support.virtual_mcu import VirtualMcu


def klipper_toml(path: str) -> str:
    return f"""
[backend]
kind = "klipper"
serial = "{path}"
lead_time_s = 0.2
[backend.axes.x]
step_pin = "PB13"
dir_pin = "!PB12"
[backend.axes.y]
step_pin = "PB10"
dir_pin = "PB2"
"""


async def status(client: CharCountingClient) -> str:
    client.writer.write(b"?")
    while True:
        line = await asyncio.wait_for(client.reader.readline(), 5.0)
        if line.startswith(b"<"):
            return line.decode().strip()


async def test_a_motiond_process_streams_a_job_to_a_klipper_mcu_and_reports_status(
    tmp_path: Path
) -> None:
    mcu = VirtualMcu().start()
    try:
        async with motiond(tmp_path, klipper_toml(mcu.path)) as served:
            for _ in range(300):
                if mcu.configured:
                    break
                await asyncio.sleep(0.01)
            assert mcu.configured
            client = await CharCountingClient.connect("127.0.0.1", served.tcp_port)
            result = await client.stream(["G21 G90", "G1 X20 Y10 F6000", "G1 X0 Y30",
                                          "G1 X10 Y10 F3000"])
            assert result.replies == ["ok"] * 4
            reports = [await status(client)]
            for _ in range(300):
                if reports[-1].startswith("<Idle"):
                    break
                await asyncio.sleep(0.02)
                reports.append(await status(client))
            assert any(r.startswith("<Run") for r in reports)
            assert reports[-1].startswith("<Idle|MPos:10.000,10.000")
            await asyncio.sleep(0.3)  # the MCU runs a lead time behind
            x_clocks, x_dirs = mcu.step_clocks(0)
            y_clocks, y_dirs = mcu.step_clocks(1)
            assert -int(x_dirs.sum()) == 800 and int(y_dirs.sum()) == 800  # X's dir is inverted
            assert len(x_clocks) == 1600 + 1600 + 800 and len(y_clocks) == 800 + 1600 + 1600
            assert np.all(np.diff(x_clocks) > 0) and mcu.shutdowns == []
            await client.close()
    finally:
        mcu.stop()
