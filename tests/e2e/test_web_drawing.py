"""From a drawing to a cut in the web UI: drop an SVG and a PNG, see the layers over the
travel, set each layer, make the job, then the usual place, frame and start. Real headless
Chromium via Playwright against motiond on a real port and clock.

Screenshots: ``artifacts/screenshots/drawing-layers.png``, ``drawing-job.png``,
``drawing-image.png``.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from playwright.async_api import Page, expect

from tests.e2e.test_web_e2e import shot
from tests.e2e.test_web_placement import idle_at, laser_ui, send, until

DATA = Path(__file__).parents[1] / "data" / "cam"


async def _set(page: Page, layer: str, key: str, value: str) -> None:
    field = page.locator(f"#drawing-layers tr[data-layer='{layer}'] [data-key='{key}']")
    if await field.evaluate("node => node.tagName") == "SELECT":
        await field.select_option(value)
    else:
        await field.fill(value)
        await field.dispatch_event("change")


async def test_an_svg_dropped_in_the_ui_becomes_a_job_that_frames_and_starts(
        tmp_path: Path) -> None:
    async with laser_ui(tmp_path) as (app, page):
        await page.locator("#file-input").set_input_files(str(DATA / "three-colours.svg"))
        dialog = page.locator("#drawing-dialog")
        await expect(dialog).to_be_visible()
        rows = page.locator("#drawing-layers tr")
        await expect(rows).to_have_count(3)
        await expect(page.locator("#drawing-status")).to_contain_text("120.0 × 90.0 mm")
        for layer in ("#0000ff", "#008000", "#ff0000"):
            await _set(page, layer, "speed_mm_min", "12000")
        await _set(page, "#0000ff", "power_pct", "30")
        await _set(page, "#0000ff", "interval_mm", "1")
        await _set(page, "#008000", "passes", "2")
        await shot(page, "drawing-layers")
        await page.locator("#drawing-generate").click()
        await expect(page.locator("#toasts")).to_contain_text("Made three-colours.gcode")
        await expect(dialog).to_be_hidden()
        job = page.locator("#job-files li[data-name='three-colours.gcode']")
        await expect(job).to_have_class("selected")
        await expect(page.locator("#view-job")).to_contain_text("planned")
        await expect(page.locator("#job-fit")).to_have_text("Fits")
        await shot(page, "drawing-job")
        gcode = (tmp_path / "jobs" / "three-colours.gcode").read_text()
        blue = gcode.split("; layer #0000ff")[1].split("; layer")[0]
        assert " S300" in blue and "F12000" in blue
        assert gcode.count("; layer #008000") == 2

        machine = app.kernel.machine
        await page.locator("#job-frame").click()
        await expect(page.locator("#state")).to_have_text("Jog")
        await until(lambda: machine.busy, False, timeout_s=20.0)
        await job.locator("button.run").click()
        await expect(page.locator("#job-state")).to_have_text("Running")
        await until(lambda: (app.kernel.jobs.progress() or {}) != {} and machine.busy, True)
        await page.locator("#job-abort").click()
        await page.locator("#confirm-ok").click()
        await expect(page.locator("#job-state")).to_have_text("Aborted")


async def test_a_photo_dropped_in_the_ui_becomes_a_dithered_engrave(tmp_path: Path) -> None:
    yy, xx = np.mgrid[0:300, 0:400]
    photo = (255 * (xx / 400) * (0.6 + 0.4 * np.sin(yy / 30.0))).clip(0, 255).astype(np.uint8)
    path = tmp_path / "portrait.png"
    buffer = io.BytesIO()
    Image.fromarray(photo).save(buffer, "PNG", dpi=(254, 254))
    path.write_bytes(buffer.getvalue())
    async with laser_ui(tmp_path) as (app, page):
        await page.locator("#file-input").set_input_files(str(path))
        await expect(page.locator("#drawing-layers tr")).to_have_count(1)
        await expect(page.locator("#drawing-status")).to_contain_text("40.0 × 30.0 mm")
        await _set(page, "image", "dither", "floyd-steinberg")
        await _set(page, "image", "power_pct", "60")
        await page.locator("#drawing-width").fill("60")
        await page.locator("#drawing-width").dispatch_event("change")
        await expect(page.locator("#drawing-status")).to_contain_text("60.0 × 45.0 mm")
        dither = page.locator("#drawing-layers tr[data-layer='image'] [data-key='dither']")
        await expect(dither).to_have_value("floyd-steinberg")  # kept across the new size
        await shot(page, "drawing-image")
        await page.locator("#drawing-generate").click()
        await expect(page.locator("#toasts")).to_contain_text("Made portrait.gcode")
        await expect(page.locator("#job-fit")).to_have_text("Does not fit")  # the overscan
        await expect(page.locator("#job-fit-text")).to_contain_text("X: 2.000 mm below")
        await send(page, "G0 X20 Y20")
        await idle_at(app, 20.0, 20.0)
        await page.locator("#zero-all").click()
        await expect(page.locator("#job-fit")).to_have_text("Fits")
        gcode = (tmp_path / "jobs" / "portrait.gcode").read_text()
        assert {s for s in gcode.split() if s.startswith("S")} == {"S0", "S600"}
        xs = [float(w[1:]) for w in gcode.split() if w.startswith("X")]
        assert max(xs) == pytest.approx(60.0 + 2.0, abs=0.01)  # 60 mm wide, and the overscan


async def test_layer_settings_saved_as_a_material_fill_the_next_drawing(tmp_path: Path) -> None:
    async with laser_ui(tmp_path) as (_, page):
        await page.locator("#file-input").set_input_files(str(DATA / "three-colours.svg"))
        await expect(page.locator("#drawing-layers tr")).to_have_count(3)
        await _set(page, "#0000ff", "power_pct", "25")
        await _set(page, "#ff0000", "passes", "3")
        await page.locator("#drawing-material-name").fill("3 mm plywood")
        await page.locator("#drawing-material-save").click()
        await expect(page.locator("#toasts")).to_contain_text("Saved the material 3 mm plywood")
        await page.locator("#drawing-cancel").click()
        await page.locator("#file-input").set_input_files(str(DATA / "three-colours.svg"))
        power = page.locator("#drawing-layers tr[data-layer='#0000ff'] [data-key='power_pct']")
        await expect(power).to_have_value("50")
        await page.locator("#drawing-material").select_option("3 mm plywood")
        await expect(power).to_have_value("25")
        passes = page.locator("#drawing-layers tr[data-layer='#ff0000'] [data-key='passes']")
        await expect(passes).to_have_value("3")
        await shot(page, "drawing-material")
    assert "3 mm plywood" in (tmp_path / "materials.json").read_text()
