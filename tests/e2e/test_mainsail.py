"""Mainsail (v2.18.0, built: ``../shared/rigs/mainsail``) in headless Chromium, through the
real Moonraker, driving motiond: the dashboard shows the machine's position and state, the
console sends a line and shows the reply, the jog and home buttons move the machine, and a
file uploaded in Mainsail runs with its progress shown.

Screenshots land in ``artifacts/screenshots/mainsail-*.png``.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from aiohttp import web
from playwright.async_api import Page, async_playwright, expect

from tests.e2e.test_moonraker import stack
from tests.e2e.test_moonraker_laser import LASER_AND_AIR
from tests.e2e.test_mqtt import mpos, tcp_report
from tests.e2e.test_web_e2e import CHROMIUM, CHROMIUM_ARGS, DESKTOP, SHOTS
from tests.support.moonraker import Moonraker
from tests.support.processes import free_port
from tests.support.rigs import RIGS

DIST = RIGS / "mainsail" / "dist"
UI_S = 30_000  # ms: Mainsail on a loaded machine
pytestmark = pytest.mark.skipif(not DIST.is_dir(), reason=f"no Mainsail rig at {DIST}")


@contextlib.asynccontextmanager
async def mainsail(tmp_path: Path, moonraker_port: int) -> AsyncIterator[str]:
    """A copy of Mainsail's dist with its config.json pointing at Moonraker, served over
    HTTP (every unknown path answers index.html, as Mainsail's router needs)."""
    root = tmp_path / "mainsail"
    shutil.copytree(DIST, root)
    config = json.loads((root / "config.json").read_text())
    config.update(hostname="127.0.0.1", port=moonraker_port)
    (root / "config.json").write_text(json.dumps(config))

    async def files(request: web.Request) -> web.StreamResponse:
        path = (root / request.match_info["path"]).resolve()
        if path.is_file() and path.is_relative_to(root):
            return web.FileResponse(path)
        return web.FileResponse(root / "index.html")

    app = web.Application()
    app.router.add_get("/{path:.*}", files)
    runner = web.AppRunner(app)
    await runner.setup()
    port = free_port()
    site = web.TCPSite(runner, "127.0.0.1", port)
    await site.start()
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        await runner.cleanup()


@contextlib.asynccontextmanager
async def browser_page(url: str) -> AsyncIterator[Page]:
    async with async_playwright() as playwright:
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            context = await browser.new_context(viewport=DESKTOP, service_workers="block")
            page = await context.new_page()
            await page.goto(url, wait_until="commit", timeout=90_000)
            yield page
        finally:
            await browser.close()


async def shot(page: Page, name: str) -> None:
    SHOTS.mkdir(parents=True, exist_ok=True)
    await page.screenshot(path=str(SHOTS / f"mainsail-{name}.png"))


JOB = "G90 G21\nM4 S300\n" + "".join(
    f"G1 X{20 + i % 2 * 40} Y{20 + i} F6000\n" for i in range(20)) + "M5\n"


async def test_mainsail_shows_and_drives_motiond(tmp_path: Path) -> None:
    async with stack(tmp_path, LASER_AND_AIR) as (served, server, _), \
            mainsail(tmp_path, server.port) as url, browser_page(url) as page:
        toolhead = page.locator(".v-card", has_text="Toolhead").first
        await expect(toolhead).to_be_visible(timeout=90_000)  # its bundle, on a busy machine
        await expect(page.get_by_text("Missing configuration")).to_have_count(0)
        await shot(page, "dashboard")
        await _air_assist_switched_from_the_dashboard(page, server)

        await page.get_by_role("button", name="ALL").click()  # G28: motiond homes X and Y
        await server.wait_for(lambda s: s["toolhead"]["homed_axes"] == "xyz",
                              toolhead=["homed_axes"])
        await _jog(page, "X", "+10")
        await _jog(page, "Y", "+1")
        await server.wait_for(lambda s: s["toolhead"]["position"][:2] == [10.0, 1.0],
                              toolhead=["position"])
        assert mpos(await tcp_report(served.tcp_port))[:2] == [10.0, 1.0]
        await expect(toolhead.locator("input").first).to_have_value("10.00", timeout=UI_S)
        await shot(page, "jogged")

        console = page.locator("textarea").first
        await console.fill("M114")
        await console.press("Enter")
        reply = page.get_by_text(re.compile(r"^X:10.0000 Y:1.0000 Z:0.0000"))
        await expect(reply.first).to_be_visible(timeout=UI_S)
        await shot(page, "console")

        await _upload_and_print(page, tmp_path, server)
        await expect(page.get_by_text("square.gcode").first).to_be_visible(timeout=UI_S)
        await server.wait_for(lambda s: s["virtual_sdcard"]["progress"] >= 0.2,
                              virtual_sdcard=["progress"])
        await server.post("/printer/print/pause")  # the progress holds still while we look
        await expect(page.get_by_text(_PERCENT).first).to_be_visible(timeout=UI_S)
        await shot(page, "paused")
        await server.post("/printer/print/resume")
        await server.wait_for(lambda s: s["print_stats"]["state"] == "complete", timeout_s=60,
                              print_stats=["state"])
        await page.wait_for_timeout(1000)
        await shot(page, "complete")
        complete = page.get_by_text(re.compile(r"^\s*Complete\s*$"))
        await expect(complete.first).to_be_visible(timeout=UI_S)

        await console.fill("G1 X250 Y250 F600")
        await console.press("Enter")
        await server.wait_for(lambda s: s["motion_report"]["live_velocity"] > 0,
                              motion_report=["live_velocity"])
        await page.get_by_role("button", name=re.compile("emergency stop", re.I)).first.click()
        status = await server.wait_for(lambda s: s["webhooks"]["state"] == "shutdown",
                                       timeout_s=5, webhooks=None)
        assert "ALARM:40" in status["webhooks"]["state_message"]
        stopped_at = mpos(await tcp_report(served.tcp_port))
        assert stopped_at[0] < 250
        await page.wait_for_timeout(1500)
        await shot(page, "emergency-stop")
        assert mpos(await tcp_report(served.tcp_port)) == stopped_at
        homed = await server.query(toolhead=["homed_axes"])
        assert homed["toolhead"]["homed_axes"] == "z", "X and Y unhomed, as Klipper's"


async def _air_assist_switched_from_the_dashboard(page: Page, server: Moonraker) -> None:
    """The Miscellaneous panel shows the laser (a slider, whose SET_PIN motiond refuses) and
    air assist (a toggle, not PWM); the toggle runs M8 through motiond's ordered path."""
    panel = page.locator(".v-card", has_text="Miscellaneous").first
    await expect(panel).to_be_visible(timeout=UI_S)
    await expect(panel.get_by_text("Laser").first).to_be_visible(timeout=UI_S)
    await panel.locator(".v-subheader", has_text="Air").first.locator("button").click()
    await server.wait_for(lambda s: s["output_pin air"]["value"] == 1.0,
                          **{"output_pin air": None})
    await shot(page, "air-assist")


_PERCENT = re.compile(r"^\s*[1-9]\d?% Paused\s*$")


async def _jog(page: Page, axis: str, step: str) -> None:
    row = page.locator("button.btnHomeAxis", has_text=axis).first.locator("xpath=..")
    await row.locator("button", has_text=step).first.click()


async def _upload_and_print(page: Page, tmp_path: Path, server: Moonraker) -> None:
    job = tmp_path / "square.gcode"
    job.write_text(JOB)
    await page.locator("input[type=file][accept*=gcode]").first.set_input_files(str(job))
