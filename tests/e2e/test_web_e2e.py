"""The web UI end to end: real headless Chromium (Debian's) driven by Playwright, against a
motiond served in this process on a real TCP port, on the real or the virtual clock.

Screenshots land in ``artifacts/screenshots/`` (desktop 1440x900 and phone 390x844).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import shutil
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from playwright.async_api import Browser, Page, async_playwright, expect

from server.api.server import http_with_api
from server.app import App
from server.config import Config
from server.offline.toolpath import plan_toolpath
from server.runtime.clock import Clock, RealClock, VirtualClock
from server.transports.websocket import HttpTransport
from tests.conftest import CORPUS, REPO, make_config
from tests.support.helpers import running

CHROMIUM = os.environ.get("MOTIOND_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
SHOTS = REPO / "artifacts" / "screenshots"
DESKTOP = {"width": 1440, "height": 900}
PHONE = {"width": 390, "height": 844}
JOB = "laser-vector-jsdc.gcode"
expect.set_options(timeout=15_000)


def e2e_config(data_dir: Path, tick_hz: float = 1000.0) -> Config:
    """A laser machine with room on both sides of the origin (the corpus jobs go negative)."""
    axis = {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000}
    return make_config(
        {
            "machine": {"name": "e2e laser 400x300"},
            "axes": {
                "x": {**axis, "min_mm": -200, "max_mm": 300},
                "y": {**axis, "min_mm": -150, "max_mm": 150},
                "z": {
                    "steps_per_mm": 400,
                    "max_rate_mm_s": 10,
                    "accel_mm_s2": 200,
                    "min_mm": -50,
                    "max_mm": 50,
                },
            },
            "stepgen": {"tick_hz": tick_hz},
            "laser": {"sample_hz": min(1000.0, tick_hz)},
            "endstops": {
                "axes": {
                    "x": {"switch_at_mm": -201, "seek_mm_s": 300},
                    "y": {"switch_at_mm": -151, "seek_mm_s": 300},
                },
                "check_hz": min(1000.0, tick_hz),
            },
            "jobs": {"data_dir": str(data_dir)},
        }
    )


@contextlib.asynccontextmanager
async def ui(
    tmp_path: Path,
    clock: Clock,
    viewport: dict[str, int] = DESKTOP,
    tick_hz: float = 1000.0,
    **context: Any,
) -> AsyncIterator[tuple[App, Page]]:
    """motiond on ``clock`` and a Chromium page showing its UI."""
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install chromium (see .ci/run)")
    async with (
        running(e2e_config(tmp_path, tick_hz), clock, transports=[http_with_api]) as app,
        async_playwright() as playwright,
    ):
        browser: Browser = await playwright.chromium.launch(
            executable_path=CHROMIUM, args=CHROMIUM_ARGS
        )
        try:
            page = await browser.new_page(viewport=viewport, **context)
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            port = next(t for t in app.transports if isinstance(t, HttpTransport)).port
            await page.goto(f"http://127.0.0.1:{port}/")
            await expect(page.locator("#connection")).to_have_attribute("data-conn", "open")
            await expect(page.locator("#state")).to_have_text("Idle")
            yield app, page
            assert errors == [], errors
        finally:
            await browser.close()


async def shot(page: Page, name: str, full_page: bool = False) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    await page.wait_for_timeout(150)  # let the canvas and the plot catch up
    await page.screenshot(path=str(SHOTS / f"{name}.png"), full_page=full_page)


async def console_send(page: Page, line: str) -> None:
    await page.locator("#console-input").fill(line)
    await page.locator("#console-input").press("Enter")


def work_x(page: Page) -> Any:
    return page.locator('#dro-body td.work[data-axis="X"]')


def work_y(page: Page) -> Any:
    return page.locator('#dro-body td.work[data-axis="Y"]')


# -- the tests ------------------------------------------------------------------------------
async def test_the_page_shows_the_machine_at_a_glance(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        await expect(page.locator("#machine-name")).to_have_text("e2e laser 400x300")
        await expect(work_x(page)).to_have_text("0.000")
        await expect(page.locator("#btn-hold")).to_be_disabled()
        await expect(page.locator("#btn-home")).to_be_enabled()
        await expect(page.locator("#console-log")).to_contain_text("Connected to e2e laser")
        await shot(page, "desktop-idle")


async def test_jogging_from_the_pad_moves_the_position_readout(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        await page.get_by_role("radio", name="10").click()
        await page.get_by_role("button", name="Jog X+", exact=True).click()
        await expect(work_x(page)).to_have_text("10.000")
        await page.get_by_role("radio", name="1", exact=True).click()
        await page.get_by_role("button", name="Jog Y-", exact=True).click()
        await page.get_by_role("button", name="Jog Y-", exact=True).click()
        await expect(work_y(page)).to_have_text("-2.000")
        await expect(page.locator("#state")).to_have_text("Idle")
    assert app.kernel.machine.stepgen.state.position_mm[:2] == (10.0, -2.0)


async def test_a_console_line_is_answered_with_ok_and_errors_with_their_meaning(
    tmp_path: Path,
) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        log = page.locator("#console-log")
        await console_send(page, "G0 X5 Y5")
        await expect(log.locator(".sent", has_text="G0 X5 Y5")).to_be_visible()
        await expect(log.locator(".ok")).to_have_count(1)
        await console_send(page, "G99")
        await expect(log.locator(".err")).to_have_text(
            "error:20 unsupported G code G99 — Unsupported or invalid G-code command"
        )
        await page.get_by_role("button", name="$G", exact=True).click()
        await expect(log.locator(".msg", has_text="[GC:G0 G54")).to_be_visible()
        await expect(work_x(page)).to_have_text("5.000")
        await shot(page, "desktop-console")


async def test_an_uploaded_corpus_job_runs_to_100_percent_and_ends_where_the_file_ends(
    tmp_path: Path,
) -> None:
    source = CORPUS / JOB
    expected_end = plan_toolpath(source.read_text().splitlines(), e2e_config(tmp_path).core, 1000)[
        "end"
    ]
    async with ui(tmp_path, VirtualClock(), tick_hz=100.0) as (app, page):
        await page.get_by_role("button", name="Jog X+", exact=True).click()
        await expect(work_x(page)).to_have_text("10.000")
        await page.locator("#file-input").set_input_files(str(source))
        row = page.locator(f'#job-files li[data-name="{JOB}"]')
        await expect(row).to_be_visible()
        await expect(page.locator("#view-job")).to_contain_text("segments")
        await shot(page, "desktop-job-preview")
        await row.get_by_role("button", name=f"Run {JOB}").click()
        progress = page.locator("#job-progress")
        await expect(progress).to_have_attribute("aria-valuenow", "100", timeout=45_000)
        await expect(page.locator("#job-state")).to_have_text("Done")
        await expect(work_x(page)).to_have_text(f"{expected_end[0]:.3f}")
        await expect(work_y(page)).to_have_text(f"{expected_end[1]:.3f}")
        await expect(page.locator("#state")).to_have_text("Idle")
        done = await page.evaluate("window.motiond.toolpath.done")
        segments = await page.evaluate("window.motiond.toolpath.path.segments")
        assert done == segments, "the whole path is drawn as cut"
        await shot(page, "desktop-job-done")
    assert app.kernel.jobs.progress().state == "done"


async def test_hold_and_resume_from_the_buttons_during_a_job(tmp_path: Path) -> None:
    (tmp_path / "jobs").mkdir()
    (tmp_path / "jobs" / "rose.nc").write_text(rose_job())
    async with ui(tmp_path, RealClock()) as (app, page):
        state = page.locator("#state")
        await page.locator('#job-files li[data-name="rose.nc"]').click()
        await expect(page.locator("#view-job")).to_contain_text("segments")
        await page.get_by_role("button", name="Run rose.nc").click()
        await expect(page.locator("#job-state")).to_have_text("Running")
        await expect(state).to_have_text("Run")
        await page.wait_for_function("window.motiond.toolpath.done > 40")
        await shot(page, "desktop-job-running")
        await page.locator("#btn-hold").click()
        await expect(state).to_have_text("Hold")
        await expect(page.locator("#job-state")).to_have_text("Paused")
        await expect(page.locator("#power")).to_have_text("0")
        held_at = await work_x(page).text_content()
        await page.wait_for_timeout(400)
        await expect(work_x(page)).to_have_text(held_at or "")
        await shot(page, "desktop-hold")
        await page.locator("#btn-resume").click()
        await expect(page.locator("#job-state")).to_have_text("Running")
        await expect(page.locator("#job-state")).to_have_text("Done", timeout=30_000)
        await expect(page.locator("#job-progress")).to_have_attribute("aria-valuenow", "100")
        await expect(state).to_have_text("Idle")
        await expect(work_x(page)).to_have_text("0.000")


def rose_job() -> str:
    """A three-petal rose and a circle cut with M4 and varying power: about five seconds."""
    lines = ["G21 G90", "M4 S0", "G0 X40 Y0"]
    for step in range(361):
        angle = math.radians(step * 0.5)
        radius = 40 * math.cos(3 * angle)
        power = 300 + 600 * abs(math.sin(3 * angle))
        lines.append(
            f"G1 X{radius * math.cos(angle):.3f} Y{radius * math.sin(angle):.3f} S{power:.0f} F6000"
        )
    lines += ["G0 X55 Y0", "G2 X55 Y0 I-55 J0 S900 F9000", "M5", "G0 X0 Y0"]
    return "\n".join(lines) + "\n"


async def test_reset_while_moving_shows_the_alarm_and_unlock_clears_it(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        await console_send(page, "G1 X150 F4000")
        await expect(page.locator("#state")).to_have_text("Run")
        await page.wait_for_timeout(200)
        await page.locator("#btn-reset").click()
        banner = page.locator("#alarm")
        await expect(banner).to_be_visible()
        await expect(page.locator("#alarm-title")).to_have_text("ALARM 3")
        await expect(page.locator("#alarm-meaning")).to_contain_text("position may be lost")
        await expect(page.locator("#state")).to_have_text("Alarm")
        await expect(page.locator("#console-log .alarm-line")).to_have_text("ALARM:3")
        await shot(page, "desktop-alarm")
        await console_send(page, "G0 X1")
        await expect(page.locator("#console-log .err")).to_contain_text("error:9")
        await page.locator("#alarm-unlock").click()
        await expect(banner).to_be_hidden()
        await expect(page.locator("#state")).to_have_text("Idle")


async def test_home_runs_the_homing_cycle_from_the_button(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        await page.get_by_role("button", name="Jog X+", exact=True).click()
        await expect(work_x(page)).to_have_text("10.000")
        await page.locator("#btn-home").click()
        await expect(page.locator("#state")).to_have_text("Home")
        await expect(page.locator("#toasts")).to_contain_text("Homing finished")
        await expect(page.locator("#state")).to_have_text("Idle")
        await expect(work_x(page)).to_have_text("-200.000")


async def test_fire_asks_for_confirmation_and_the_laser_can_be_stopped(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        fire = page.locator("#btn-fire")
        await fire.click()
        dialog = page.locator("#fire-dialog")
        await expect(dialog).to_be_visible()
        await dialog.get_by_role("button", name="Cancel").click()
        await expect(dialog).to_be_hidden()
        assert app.kernel.modules["laser"].power == 0.0  # type: ignore[attr-defined]
        await fire.click()
        await page.locator("#fire-power").fill("2")
        await page.locator("#fire-duration").fill("20")
        await shot(page, "desktop-fire-dialog")
        await dialog.get_by_role("button", name="Fire").click()
        await expect(fire).to_have_text(re.compile("Stop"))
        await expect(page.locator("#power")).to_have_text("2.0")
        await fire.click()
        await expect(fire).to_have_text(re.compile("Fire"))
    assert app.kernel.modules["laser"].power == 0.0  # type: ignore[attr-defined]


async def test_the_page_works_on_a_phone_sized_screen(tmp_path: Path) -> None:
    (tmp_path / "jobs").mkdir()
    shutil.copy(CORPUS / JOB, tmp_path / "jobs" / JOB)
    async with ui(tmp_path, RealClock(), PHONE, is_mobile=True, has_touch=True) as (app, page):
        width = await page.evaluate("document.scrollingElement.scrollWidth")
        assert width <= PHONE["width"], "nothing sticks out sideways"
        await page.get_by_role("button", name="Jog Y+", exact=True).tap()
        await expect(work_y(page)).to_have_text("10.000")
        await shot(page, "phone-top")
        await page.locator(f'#job-files li[data-name="{JOB}"]').tap()
        await expect(page.locator("#view-job")).to_contain_text("segments")
        await page.evaluate("scrollTo(0, document.querySelector('.card-view').offsetTop - 60)")
        await shot(page, "phone-toolpath")
        await page.evaluate("window.scrollTo(0, 0)")
        await shot(page, "phone-full", full_page=True)


async def test_a_file_dropped_on_the_drop_zone_is_uploaded(tmp_path: Path) -> None:
    async with ui(tmp_path, RealClock()) as (app, page):
        data = await page.evaluate_handle(
            """() => { const t = new DataTransfer();
                       t.items.add(new File(["G0 X1 Y1\\nG1 X5 F600\\n"], "dropped.nc"));
                       return t; }"""
        )
        await page.locator("#dropzone").dispatch_event("drop", {"dataTransfer": data})
        await expect(page.locator('#job-files li[data-name="dropped.nc"]')).to_be_visible()
        await expect(page.locator("#toasts")).to_contain_text("Uploaded dropped.nc")
    assert (tmp_path / "jobs" / "dropped.nc").read_text() == "G0 X1 Y1\nG1 X5 F600\n"
