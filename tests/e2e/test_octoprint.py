"""OctoPrint itself (PyPI, its own virtual environment) as the host of motiond's pty.

One OctoPrint server runs for the module (it takes 10-30 s to start here); each test starts a
motiond on the same pty path, connects OctoPrint to it through its REST API, does what a user
does in OctoPrint's UI, and checks what the machine did. OctoPrint keeps its own timeouts
(30 s without a line, 3 s once it has seen the busy keep-alive): a single move of 100 s holds
an ``ok`` through all of them, as a long laser line does. Every online feature is off (see
:mod:`tests.support.octoprint`).
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import aiohttp
import pytest
from playwright.async_api import async_playwright, expect

from server.app import App
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.serial import SerialTransport
from tests.conftest import make_config
from tests.e2e.test_web_e2e import CHROMIUM, CHROMIUM_ARGS
from tests.support.octoprint import Api, OctoPrint
from tests.support.senders import wait_for

LASER = {"minimum_power": 0.1, "maximum_power": 0.8, "maximum_s_value": 1000}
# OctoPrint's defaults but its communication timeout (30 s), shortened so that a move three
# times as long takes 15 s, not 100: motiond's keep-alive (every 2 s) must hold it either way
TIMEOUTS_S: dict[str, float] = {"communication": 5.0}
COMMUNICATION_TIMEOUT_S = TIMEOUTS_S["communication"]  # serial.timeout.communication
CANCEL_SCRIPT = "M410\nM5\n"  # docs/octoprint.md's cancel script for a laser
_SENT_M112 = re.compile(r"Send: (N\d+ )?M112")  # (the alarm's notification names M112)
_PAUSE_EVENT = re.compile(r"event: PrintPaused \(Payload: .*?'position': \{[^}]*'x': ([-\d.]+)")


@pytest.fixture(scope="module")
def octoprint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OctoPrint]:
    folder = tmp_path_factory.mktemp("octoprint")
    server = OctoPrint(folder / "basedir", folder / "ttyMotiond", timeouts_s=TIMEOUTS_S,
                       scripts={"afterPrintCancelled": CANCEL_SCRIPT})
    try:
        server.start()
        yield server
    finally:
        server.close()  # also when it never answered: no OctoPrint outlives the tests


class Run:
    """One test's motiond and OctoPrint's API; ``serial`` is this test's part of serial.log."""

    def __init__(self, app: App, api: Api, server: OctoPrint) -> None:
        self.app, self.api, self.server = app, api, server
        self._serial_from = len(server.serial_log())
        self._log_from = len(server.log())

    @property
    def serial(self) -> str:
        return self.server.serial_log()[self._serial_from:]

    @property
    def log(self) -> str:
        return self.server.log()[self._log_from:]

    @property
    def machine_x(self) -> float:
        return float(self.app.kernel.machine.stepgen.state.position_mm[0])

    @property
    def moving(self) -> bool:
        return not self.app.kernel.machine.stepgen.idle

    def laser_power(self) -> float:
        return float(self.app.kernel.modules["laser"].power)  # type: ignore[attr-defined]


@contextlib.asynccontextmanager
async def machine(server: OctoPrint, *, connect: bool = True) -> AsyncIterator[Run]:
    config = make_config(serial={"pty": str(server.port_path)}, laser=LASER)
    app = App(config, clock=RealClock(), transports=[SerialTransport])
    task = asyncio.create_task(app.run())
    await asyncio.wait_for(app.ready.wait(), 10)
    try:
        async with server.api() as api:
            run = Run(app, api, server)
            if connect:
                await api.connect()
                await api.wait_state("Operational", 20)
            try:
                yield run
            finally:
                with contextlib.suppress(AssertionError, aiohttp.ClientError):
                    await api.disconnect()
                    await api.wait_state(("Offline", "Closed"), 10)
        assert "Externally triggered heatup" not in run.log, "M105 answered on one ok line"
        assert "Communication timeout" not in run.serial, run.serial[-3000:]
    finally:
        app.request_stop()
        await asyncio.wait_for(task, 10)


async def click_in_control_tab(server: OctoPrint, button: str) -> None:
    """Open OctoPrint's web UI in headless Chromium (logged in as its local user), go to the
    Control tab and click ``button`` once it is enabled (the printer connected)."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install chromium (see .ci/run)")
    async with async_playwright() as playwright:
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = await browser.new_page()
            await page.goto(f"{server.url}/", timeout=120_000)  # 20 s here, with its assets
            await page.locator('a[href="#control"]').click(timeout=60_000)
            target = page.get_by_role("button", name=button, exact=True)
            await expect(target).to_be_enabled(timeout=30_000)
            await target.click()
        finally:
            await browser.close()


async def printing(run: Run, name: str, lines: list[str]) -> None:
    await run.api.upload(name, "\n".join(lines) + "\n")
    await run.api.print_file(name)
    await run.api.wait_state("Printing", 10)


async def test_octoprint_connects_to_a_machine_in_alarm_and_its_unlock_button_unlocks_it(
    octoprint: OctoPrint,
) -> None:
    """No terminal: the user connects, sees the alarm, clicks Reconnect (which must not
    unlock: Grbl clears an alarm only on purpose), then, in OctoPrint's web UI in Chromium,
    the Control tab's "Unlock" button (docs/octoprint.md's custom control, M999)."""
    async with machine(octoprint, connect=False) as run:
        run.app.kernel.machine.emergency_stop()  # ALARM:40, as after an M112
        await run.api.connect()
        await run.api.wait_state("Operational", 20)
        await wait_for(lambda: "Recv: Cap:EMERGENCY_PARSER:1" in run.serial
                       and 'Unknown command: "unsupported M code M21"' in run.serial,
                       10, "OctoPrint's M115 and M21 answered")
        await run.api.disconnect()
        await run.api.wait_state(("Offline", "Closed"), 10)
        await run.api.connect()
        await run.api.wait_state("Operational", 20)
        still_locked = run.app.kernel.state is MachineState.ALARM
        await click_in_control_tab(octoprint, "Unlock")
        await wait_for(lambda: run.app.kernel.state is MachineState.IDLE, 5, "Unlock (M999)")
        await run.api.post("/api/printer/printhead", {"command": "jog", "x": 10, "y": 5})
        await wait_for(lambda: run.machine_x == pytest.approx(10.0), 5, "a jog after Unlock")
        state = await run.api.state()
    assert still_locked, "a reconnect never clears an alarm"
    assert state == "Operational"
    assert "Error:" not in run.serial and not _SENT_M112.search(run.serial)
    assert re.search(r"Send: (N\d+ )?M999", run.serial), "the button sent M999"


async def test_octoprint_prints_a_job_and_is_done_only_when_motion_is_done(
    octoprint: OctoPrint,
) -> None:
    segments = [f"G1 X{x / 2:g} Y{(x % 4) / 2:g}" for x in range(1, 41)]
    job = ["G21", "G90", "M4 S200", "G1 F3000", *segments, "G1 X60 Y0 F1200", "M5"]
    async with machine(octoprint) as run:
        await printing(run, "job.gcode", job)
        moving_when_finishing = False
        while (state := await run.api.state()) != "Operational":
            moving_when_finishing |= state.startswith("Finishing") and run.moving
            await asyncio.sleep(0.02)
        moving_when_done = run.moving
        completion = (await run.api.job())["progress"]["completion"]
        position = run.app.kernel.machine.stepgen.state.position_mm
    assert moving_when_finishing, "OctoPrint waited (Finishing) while the last move ran"
    assert not moving_when_done and completion == 100
    assert position[:2] == pytest.approx((60.0, 0.0))


async def test_octoprint_pauses_within_two_seconds_knowing_where_and_resumes_to_the_end(
    octoprint: OctoPrint,
) -> None:
    job = ["G21", "G90", "G1 F1200", *(f"G1 X{x}" for x in range(1, 121))]  # 1 mm, 6 s
    async with machine(octoprint) as run:
        await printing(run, "pause.gcode", job)
        await wait_for(lambda: run.machine_x > 20, 10, "the job under way")
        started_s = time.monotonic()
        await run.api.job_command("pause", "pause")
        await run.api.wait_state("Paused", 5)
        paused_s = time.monotonic() - started_s
        stopped, paused_x = not run.moving, run.machine_x
        await wait_for(lambda: _PAUSE_EVENT.search(run.log) is not None, 5, "PrintPaused")
        reported = _PAUSE_EVENT.search(run.log)
        await asyncio.sleep(0.5)
        still_x = run.machine_x
        await run.api.job_command("pause", "resume")
        await run.api.wait_state("Printing", 5)
        await run.api.wait_state("Operational", 20)
        end_x = run.machine_x
    assert paused_s < 2.0 and stopped and still_x == paused_x
    assert reported is not None and float(reported.group(1)) == pytest.approx(paused_x, abs=1e-3)
    assert "no parseable position" not in run.serial.lower()
    assert end_x == pytest.approx(120.0)


async def test_octoprint_cancel_with_m410_stops_motion_and_the_laser_within_a_second(
    octoprint: OctoPrint,
) -> None:
    job = ["G21", "G90", "M3 S300", "G1 F600", *(f"G1 X{x}" for x in range(10, 101, 10))]
    async with machine(octoprint) as run:
        await printing(run, "cut.gcode", job)
        await wait_for(lambda: run.machine_x > 5 and run.laser_power() > 0, 10, "cutting")
        started_s = time.monotonic()
        await run.api.job_command("cancel")
        await wait_for(lambda: not run.moving and run.laser_power() == 0.0, 3, "the stop")
        stopped_s = time.monotonic() - started_s
        stopped_x = run.machine_x
        await run.api.wait_state("Operational", 10)
        await asyncio.sleep(1.0)
        modal = run.app.kernel.machine.interpreter.gc_report()
        later_x = run.machine_x
    assert stopped_s < 1.0, f"stopped {stopped_s:.2f} s after cancel"
    assert later_x == stopped_x < 100 and " M5 " in modal, modal
    assert re.search(r"Send: (N\d+ )?M410", run.serial), "OctoPrint sent the cancel script"


async def test_octoprint_keeps_the_connection_through_a_long_move_and_a_refused_line(
    octoprint: OctoPrint,
) -> None:
    async with machine(octoprint) as run:
        # one move of 17 s (17 mm at 1 mm/s): with the moves back queued behind it, the
        # planner is full and the ok of a line after them is held for the whole move
        await run.api.terminal("G1 X17 F60", "G0 X500", "G1 X0 F3000", "G1 X5", "G1 X0",
                               "G1 X5")
        await wait_for(lambda: run.moving, 5, "the long move")
        started_s = time.monotonic()
        await wait_for(lambda: not run.moving and run.machine_x == 5.0, 60, "the moves")
        held_s = time.monotonic() - started_s
        state = await run.api.state()
        kernel_state = run.app.kernel.state
    assert held_s > 3 * COMMUNICATION_TIMEOUT_S
    assert state == "Operational" and kernel_state is MachineState.IDLE
    assert "Recv: echo:busy: processing" in run.serial
    refused = [line for line in run.serial.splitlines() if "(code 40)" in line]
    assert refused and "Recv: echo:" in refused[0], "refused with echo:, not Error:"
    assert "Error:" not in run.serial


async def test_octoprint_in_alarm_stays_connected_when_home_or_a_jog_is_clicked_and_shows_why(
    octoprint: OctoPrint,
) -> None:
    """Home (``G28 X0 Y0``) and a jog (``G91`` first) as OctoPrint's Control tab posts them,
    with the machine in alarm: each line is refused with ``echo:`` and ``ok`` (never
    ``Error:``, on which OctoPrint sends M112 and goes offline), and OctoPrint's notification
    list (its bundled plugin, shown in its sidebar) says which alarm and how to unlock."""
    async with machine(octoprint, connect=False) as run:
        run.app.kernel.machine.emergency_stop()  # ALARM:40, as after an M112
        await run.api.connect()
        await run.api.wait_state("Operational", 20)
        await run.api.post("/api/printer/printhead", {"command": "home", "axes": ["x", "y"]})
        await run.api.post("/api/printer/printhead", {"command": "jog", "x": 10})
        await wait_for(lambda: run.serial.count("(code 9)") >= 2, 10, "both refused")
        await asyncio.sleep(1.0)  # OctoPrint would be going offline by now
        state = await run.api.state()
        notices = (await run.api.get("/api/plugin/action_command_notification"))["notifications"]
        still_locked = run.app.kernel.state is MachineState.ALARM
    assert state == "Operational" and still_locked and run.machine_x == 0.0
    assert not _SENT_M112.search(run.serial) and "Error:" not in run.serial
    assert re.search(r"Send: (N\d+ )?G28", run.serial), "OctoPrint sent the Home click's G28"
    messages = [notice["message"] for notice in notices]
    assert any("ALARM:40" in text and "M999" in text for text in messages), messages
