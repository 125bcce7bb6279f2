"""Faults between motiond and a Klipper MCU: lost blocks, silence, restarts, bad config."""

from __future__ import annotations

import asyncio
import time

import pytest

from server.app import App
from server.backends.klipper.backend import KlipperBackend
from server.errors import Alarm
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from tests.integration.test_klipper_backend import LASER, check_steps, run_job
from tests.support.helpers import running, submit_all
from tests.support.klipper_machine import PINS, klipper_config, klipper_machine
from tests.support.virtual_mcu import VirtualMcu


async def wait_for_alarm(app: App, limit_s: float = 3.0) -> float:
    """Seconds until the machine is in ALARM (fails after ``limit_s``)."""
    start = time.monotonic()
    while app.kernel.state is not MachineState.ALARM:
        assert time.monotonic() - start < limit_s, "no alarm"
        await asyncio.sleep(0.005)
    return time.monotonic() - start


async def test_lost_and_corrupted_blocks_are_sent_again_and_no_step_is_lost(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        await submit_all(app, ["G1 X30 Y20 F6000"])
        await asyncio.sleep(0.1)
        mcu.drop_blocks, mcu.corrupt_blocks = 2, 0
        await asyncio.sleep(0.15)
        mcu.corrupt_blocks = 2
        await run_job(app, ["G1 X5 Y40", "G1 X60 Y10"])
        assert mcu.naks_sent >= 2 and backend.mcu.link.retransmits >= 2
        assert check_steps(app, mcu) > 5000


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["silent", "restart"])
async def test_an_mcu_that_stops_answering_or_restarts_alarms_within_a_second_tools_off(
    mcu: VirtualMcu, fault: str
) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])
        await asyncio.sleep(0.5)
        assert backend.output("PA8") > 0
        mcu.mute() if fault == "silent" else mcu.restart()
        assert await wait_for_alarm(app) < 1.0
        assert app.kernel.alarm_code == Alarm.BACKEND_FAILED
        reason = ("stopped answering|does not answer|acknowledged none" if fault == "silent"
                  else "restart")
        assert any(word in app.kernel.alarm_message for word in reason.split("|")), (
            app.kernel.alarm_message)
        assert backend.output("PA8") == 0.0 and app.kernel.modules["laser"].power == 0.0
        assert not app.kernel.machine.stepgen.state.moving
        if fault == "restart":  # the fresh MCU is configured again, and moves after $X
            for _ in range(300):
                if backend.ready:
                    break
                await asyncio.sleep(0.01)
            assert backend.ready and mcu.configured
            assert all(out.events[-1][1] == 0 for out in mcu.outputs.values() if out.pin == "PA8")
            await submit_all(app, ["$X", "G91", "G1 Y2 F3000"])
            await app.kernel.machine.wait_idle()
            await asyncio.sleep(backend.lead_s + 0.1)
            clocks, _ = mcu.step_clocks(backend.axes[1].oid)
            assert len(clocks) == 160


async def test_an_unknown_pin_is_a_config_error_and_the_mcu_is_never_configured(
    mcu: VirtualMcu
) -> None:
    pins = {**PINS, "y": {**PINS["y"], "step_pin": "PZ9"}}
    config = klipper_config(mcu.path)
    config.core.backend.axes = config.core.backend.axes | {
        "y": type(config.core.backend.axes["y"])(**pins["y"])}
    async with running(config, clock=RealClock()) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        for _ in range(200):
            if backend.fault:
                break
            await asyncio.sleep(0.01)
        assert backend.fault is not None and "unknown pin 'PZ9'" in backend.fault
        assert "[backend.axes.y]" in backend.fault
        assert not mcu.configured and not backend.ready
        assert await wait_for_alarm(app) < 1.0
        assert "unknown pin 'PZ9'" in app.kernel.alarm_message


async def test_an_mcu_configured_differently_is_reported_and_never_driven(
    mcu: VirtualMcu
) -> None:
    mcu.configured, mcu.crc = True, 0x1234
    async with running(klipper_config(mcu.path), clock=RealClock()) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        assert await wait_for_alarm(app) < 1.0
        assert "configured differently" in app.kernel.alarm_message
        assert not backend.ready
        names = {name for _, name, _ in mcu.commands}
        assert not names & {"allocate_oids", "queue_step", "finalize_config"}


async def test_an_mcu_shutdown_becomes_an_alarm_naming_its_reason_tools_off(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend)
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])
        await asyncio.sleep(0.4)
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        assert await wait_for_alarm(app) < 1.0
        assert "the MCU shut down: Rescheduled timer in the past" in app.kernel.alarm_message
        assert backend.output("PA8") == 0.0 and app.kernel.modules["laser"].power == 0.0
        assert mcu.output_events("PA8")[-1][1] == 0


async def test_a_shutdown_a_busy_host_reads_late_keeps_its_reason(mcu: VirtualMcu) -> None:
    """The shutdown message waits in the pty while the host's loop is busy: its clock is
    then well behind the fit, which is no restart (a restarted MCU's clock goes backwards)."""
    async with klipper_machine(mcu, laser=LASER) as app:
        await submit_all(app, ["M3 S800", "G1 X100 F3000"])
        await asyncio.sleep(0.4)
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        time.sleep(0.1)  # noqa: ASYNC251 - the host's loop is busy while the message waits
        await wait_for_alarm(app)
        assert "the MCU shut down: Rescheduled timer in the past" in app.kernel.alarm_message


async def test_the_emergency_stop_goes_out_at_once_before_every_message_not_yet_sent(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        await submit_all(app, ["G1 X100 F6000"])
        await asyncio.sleep(0.3)
        mcu.mute()  # nothing is acknowledged any more: the window fills, messages wait
        link, dictionary = backend.mcu.link, backend.mcu.dictionary
        for _ in range(40):
            link.send(dictionary.encode("get_clock"))
        await asyncio.sleep(0.05)
        assert link.queued_bytes > 0
        inflight = link.in_flight
        backend.halt()
        waiting = [dictionary.decode(message)[0][0] for message in link.queued()]
        assert "queue_step" not in waiting and "get_clock" not in waiting  # plain sends dropped
        # written at once in a block of its own, though the window was full
        assert link.in_flight == inflight + 1
        assert dictionary.decode(link.inflight_payloads()[-1]) == [("emergency_stop", {})]
