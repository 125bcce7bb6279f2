"""Placing, checking and framing a job in the web UI, with the override and air-assist buttons:
real headless Chromium (Debian's) via Playwright against motiond on a real port and clock.

Screenshots: ``artifacts/screenshots/placed-job.png`` and ``frame-button.png``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Page, async_playwright, expect

from server.api.server import http_with_api
from server.app import App
from server.runtime.clock import RealClock
from server.transports.websocket import HttpTransport
from tests.conftest import CORPUS, make_config
from tests.e2e.test_web_e2e import CHROMIUM, CHROMIUM_ARGS, DESKTOP, shot
from tests.support.helpers import running

JOB = "laser-vector-jsdc.gcode"  # X 0..102.4, Y -58.1..0: origin top-left


@contextlib.asynccontextmanager
async def laser_ui(tmp_path: Path) -> AsyncIterator[tuple[App, Page]]:
    """A 400 x 300 laser with air assist on M8/M9 (the default machine's shape), its travel
    from 0, and the UI in Chromium with the corpus job stored."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install chromium (see .ci/run)")
    config = make_config(machine={"name": "laser 400x300", "laser_mode": True},
                         laser={"pin": "laser", "maximum_s_value": 1000},
                         switch={"air": {"pin": "air", "on_mcode": 8, "off_mcode": 9}},
                         jobs={"data_dir": str(tmp_path), "frame_feed_mm_min": 4000})
    async with (
        running(config, RealClock(), transports=[http_with_api]) as app,
        async_playwright() as playwright,
    ):
        await app.kernel.jobs.save(JOB, (CORPUS / JOB).read_bytes())
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = await browser.new_page(viewport=DESKTOP)
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            port = next(t for t in app.transports if isinstance(t, HttpTransport)).port
            await page.goto(f"http://127.0.0.1:{port}/")
            await expect(page.locator("#state")).to_have_text("Idle")
            yield app, page
            assert [e for e in errors if "error:47" not in e] == [], errors
        finally:
            await browser.close()


async def send(page: Page, line: str) -> None:
    await page.locator("#console-input").fill(line)
    await page.locator("#console-input").press("Enter")


async def until(read: Callable[[], Any], value: Any, timeout_s: float = 10.0) -> None:
    """Wait until ``read()`` equals ``value`` (the machine, read in this process)."""
    async with asyncio.timeout(timeout_s):
        while read() != value:  # noqa: ASYNC110 - the machine has no event for each value
            await asyncio.sleep(0.02)


async def idle_at(app: App, x: float, y: float) -> None:
    machine = app.kernel.machine
    await until(lambda: (machine.stepgen.state.position_mm[:2], machine.busy), ((x, y), False))


async def test_place_check_and_frame_a_job_in_the_ui(tmp_path: Path) -> None:
    async with laser_ui(tmp_path) as (app, page):
        jobs, machine = app.kernel.jobs, app.kernel.machine
        await page.locator(f"#job-files li[data-name='{JOB}'] .file-main").click()
        await expect(page.locator("#job-fit")).to_have_text("Does not fit")
        await expect(page.locator("#job-fit-text")).to_contain_text("Y: 58.115 mm below")
        await page.locator(f"#job-files li[data-name='{JOB}'] button.run").click()
        await expect(page.locator(".toasts")).to_contain_text("error:47")
        assert jobs.progress() is None and machine.stepgen.state.position_mm == (0.0, 0.0, 0.0)

        await send(page, "G0 X20 Y200")
        await idle_at(app, 20.0, 200.0)
        await page.locator("#zero-all").click()
        await until(lambda: machine.interpreter.wco(), (20.0, 200.0, 0.0))
        await expect(page.locator("#job-fit")).to_have_text("Fits")
        await expect(page.locator("#job-size")).to_contain_text("102.4 × 58.1 mm")
        await shot(page, "placed-job")
        await page.locator("[data-colour='power']").click()
        await expect(page.locator(".legend-unit")).to_have_text("% power")
        await expect(page.locator("#legend-max")).to_have_text("8")  # S80 of 1000
        await shot(page, "power-view")
        await page.locator("[data-colour='speed']").click()
        await expect(page.locator(".legend-unit")).to_have_text("mm/min")

        await send(page, "G0 X5 Y5")
        await idle_at(app, 25.0, 205.0)
        await page.locator("#go-zero").click()
        await idle_at(app, 20.0, 200.0)

        await page.locator("#wcs-select").select_option("G55")
        await until(lambda: machine.interpreter.modal_snapshot()["wcs"], "G55")
        await expect(page.locator("#job-fit")).to_have_text("Does not fit")
        await page.locator("#wcs-select").select_option("G54")
        await expect(page.locator("#job-fit")).to_have_text("Fits")

        await page.locator("#job-frame").click()
        await expect(page.locator("#state")).to_have_text("Jog")
        await shot(page, "frame-button")
        low = app.kernel.machine.interpreter.work_position((0.0, 0.0, 0.0))
        assert low == (-20.0, -200.0, 0.0)
        await until(lambda: machine.busy, False, timeout_s=20.0)
        x, y, _ = machine.stepgen.state.position_mm
        assert (x, y) == pytest.approx((20.0, 200.0 - 58.115), abs=0.01), "back at its corner"
        assert jobs.progress() is None, "framing is not a job"


async def test_override_and_air_buttons_change_the_machine(tmp_path: Path) -> None:
    async with laser_ui(tmp_path) as (app, page):
        machine = app.kernel.machine
        await page.locator("[data-override='feed:+10']").click()
        await until(lambda: machine.feed_override, 110)
        await expect(page.locator("#ov-feed")).to_have_text("110%")
        await page.locator("[data-override='rapid:=50']").click()
        await until(lambda: machine.rapid_override, 50)
        await expect(page.locator("[data-override='rapid:=50']")).to_have_attribute(
            "aria-pressed", "true")
        await page.locator("[data-override='spindle:-10']").click()
        await until(lambda: machine.spindle_override, 90)
        await page.locator("[data-override='feed:=100']").click()
        await until(lambda: machine.feed_override, 100)

        air = page.locator("[data-module='switch.air']")
        await expect(air).to_have_text("Air off")
        await air.click()
        await until(lambda: app.kernel.modules["switch.air"].status()["on"], True)
        await expect(air).to_have_attribute("aria-pressed", "true")
        await air.click()
        await until(lambda: app.kernel.modules["switch.air"].status()["on"], False)
