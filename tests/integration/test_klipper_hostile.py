"""The board is untrusted, and the host may die: the output watchdog, a board that talks
nonsense or comes back as another MCU, a bomb of a dictionary, expected faults in one line."""

from __future__ import annotations

import asyncio
import logging
import time
import zlib

import pytest

from server.backends.klipper.backend import KlipperBackend
from server.errors import Alarm
from server.runtime.clock import RealClock
from tests.integration.test_klipper_faults import wait_for_alarm
from tests.support.helpers import running, submit_all
from tests.support.klipper_dictionary import compressed
from tests.support.klipper_machine import klipper_config, klipper_machine
from tests.support.virtual_mcu import VirtualMcu

LASER = {"pin": "PA8"}


@pytest.mark.slow
async def test_an_output_on_is_refreshed_within_its_max_duration_and_a_hung_host_lets_it_go_off(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu, max_duration_s=0.3, laser=LASER) as app:
        config = next(p for _, name, p in mcu.commands if name == "config_pwm_out")
        assert config["max_duration"] == int(0.3 * mcu.clock_hz)  # the firmware's watchdog
        await submit_all(app, ["M3 S800", "G1 X20 F600"])  # 2 s with the laser on
        await asyncio.sleep(1.5)
        assert mcu.shutdowns == [], "refreshed in time while motiond lives"
        events = [e for e in mcu.output_events("PA8") if e[1] == 204]
        assert len(events) >= 1.2 / 0.15, "sent again every half max_duration"
        time.sleep(0.7)  # noqa: ASYNC251 - motiond hangs: nothing refreshes the laser
        await asyncio.sleep(0.05)
        assert mcu.shutdowns[:1] == ["Missed scheduling of next hard pwm event"]
        assert mcu.output_events("PA8")[-1][1] == 0, "the board turned the laser off"
        await wait_for_alarm(app)  # the late steps, or the board's shutdown, whichever is read
        assert any(why in app.kernel.alarm_message for why in ("not sent in time", "Missed"))


async def test_a_board_that_talks_nonsense_gets_the_emergency_stop_before_the_link_closes(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])
        await asyncio.sleep(0.5)
        assert mcu.output_events("PA8")[-1][1] == 204
        with mcu.lock:
            mcu._send_block(bytes([0x7F]))  # a well-framed block with a message id it never had
        assert await wait_for_alarm(app) < 0.6
        assert "unknown message id" in app.kernel.alarm_message
        await asyncio.sleep(0.1)
        assert mcu.shutdowns[:1] == ["Command request"], "the emergency stop reached it"
        assert mcu.output_events("PA8")[-1][1] == 0, "the laser is off at the board"


async def test_a_board_that_comes_back_as_another_mcu_is_an_alarm_naming_the_difference(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        with mcu.lock:
            mcu.data["config"] |= {"MCU": "stm32f407xx", "CLOCK_FREQ": 168_000_000}
            mcu.blob = compressed(mcu.data)
            mcu.restart()
        await wait_for_alarm(app)
        await asyncio.sleep(1.5)  # the reconnection
        assert backend.fault is not None and "a different MCU" in backend.fault
        assert "MCU stm32f103xe -> stm32f407xx" in backend.fault
        assert "CLOCK_FREQ 72000000 -> 168000000" in backend.fault
        assert not mcu.configured and not backend.ready


async def test_a_dictionary_that_inflates_beyond_its_bound_is_refused(
    mcu: VirtualMcu, caplog: pytest.LogCaptureFixture
) -> None:
    mcu.blob = zlib.compress(b"{" + b" " * 6_000_000, 9)  # 6 MB from a few kB
    async with running(klipper_config(mcu.path), clock=RealClock()) as app:
        assert await wait_for_alarm(app, 5.0) < 5.0
        assert "inflates beyond" in app.kernel.alarm_message
        assert app.kernel.alarm_code == Alarm.BACKEND_FAILED
        assert not mcu.configured


async def test_a_missing_device_is_an_alarm_in_one_log_line_without_a_traceback(
    caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    async with running(klipper_config("/dev/motiond-no-such-mcu"), clock=RealClock()) as app:
        await wait_for_alarm(app)
        assert "cannot open /dev/motiond-no-such-mcu: No such file" in app.kernel.alarm_message
    faults = [r for r in caplog.records if "no-such-mcu" in r.getMessage()]
    assert faults and not any(r.exc_info for r in faults)


async def test_a_board_found_shut_down_is_restarted_then_configured(mcu: VirtualMcu) -> None:
    with mcu.lock:
        mcu.shutdown("Rescheduled timer in the past")  # before motiond ever spoke to it
    async with klipper_machine(mcu) as app:
        assert mcu.resets == 1 and mcu.configured and mcu.shutdown_reason is None
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.fault is None


async def test_a_board_still_configured_by_an_earlier_motiond_is_restarted_not_reused(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu):
        pass
    assert mcu.configured and mcu.resets == 0
    async with klipper_machine(mcu):  # its outputs could be on from before: start it over
        assert mcu.resets == 1 and mcu.configured
