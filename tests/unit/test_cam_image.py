"""Images become raster engraves: the exposure the planner's blocks give each pixel follows
its gray level (grayscale) or its local mean (dithering), every burnt pixel at full speed,
white runs crossed as travel."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest
from PIL import Image

from server.cam.job import make_job, read_drawing
from server.cam.model import layer_settings
from tests.conftest import make_config
from tests.support.burn import burn

PITCH_MM = 0.1


def _photo(columns: int = 240, rows: int = 120) -> np.ndarray:
    """A gray test picture (0..255): a horizontal ramp, a dark disc, a light band."""
    x = np.linspace(0.0, 1.0, columns)[None, :].repeat(rows, axis=0)
    yy, xx = np.mgrid[0:rows, 0:columns]
    picture = 255.0 * x
    picture[(xx - columns * 0.3) ** 2 + (yy - rows * 0.5) ** 2 < (rows * 0.3) ** 2] = 40.0
    picture[rows // 5: rows // 5 + 6, :] = 200.0
    return picture.round().astype(np.uint8)


def _png(pixels: np.ndarray, dpi: float = 25.4 / PITCH_MM) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(pixels, mode="L").save(buffer, format="PNG", dpi=(dpi, dpi))
    return buffer.getvalue()


def _engrave(pixels: np.ndarray, **settings: object) -> tuple[str, np.ndarray]:
    drawing = read_drawing(_png(pixels), "photo.png")
    layer = drawing.layers[0]
    layer.settings = layer_settings({"power": 100, "interval": PITCH_MM, **settings},
                                    layer.settings)
    gcode = make_job(drawing)
    return gcode, _exposure(gcode, pixels.shape)


def _exposure(gcode: str, shape: tuple[int, ...]) -> np.ndarray:
    """Per pixel: the burnt length times S / S max over the pixel's width (M4: the energy
    per mm is S over the nominal speed, whatever the speed), from the planned blocks."""
    rows, columns = shape
    burnt = burn(gcode, make_config())
    assert np.allclose(burnt.entry_mm_s, burnt.nominal_mm_s, rtol=0.01), "a pixel burnt slow"
    exposure = np.zeros(shape)
    for (x0, y0, x1, _), s in zip(burnt.segments, burnt.s_values, strict=True):
        row = rows - 1 - int(np.floor(y0 / PITCH_MM))
        first, last = sorted((x0 / PITCH_MM, x1 / PITCH_MM))
        for column in range(int(np.floor(first)), int(np.ceil(last))):
            covered = min(last, column + 1) - max(first, column)
            if covered > 0 and 0 <= column < columns:
                exposure[row, column] += covered * s / 1000.0
    return exposure


def test_grayscale_exposure_follows_each_pixel_within_4_percent() -> None:
    pixels = _photo()
    gcode, exposure = _engrave(pixels, dither="grayscale")
    darkness = 1.0 - pixels / 255.0
    error = np.abs(exposure - darkness).mean()
    assert error <= 0.04, f"MAE {error:.4f}"
    assert "M4" in gcode and "M3" not in gcode


@pytest.mark.parametrize("method", ["floyd-steinberg", "jarvis", "stucki"])
def test_dithered_exposure_keeps_the_local_gray_level(method: str) -> None:
    pixels = _photo()
    _, exposure = _engrave(pixels, dither=method)
    assert set(np.unique(exposure.round(3))) <= {0.0, 1.0}
    darkness = 1.0 - pixels / 255.0

    def blocks(values: np.ndarray) -> np.ndarray:
        return values.reshape(values.shape[0] // 8, 8, values.shape[1] // 8, 8).mean(axis=(1, 3))

    error = np.abs(blocks(exposure) - blocks(darkness)).mean()
    assert error <= 0.04, f"{method}: MAE of 8x8 means {error:.4f}"


def test_threshold_burns_exactly_the_dark_half() -> None:
    pixels = _photo()
    _, exposure = _engrave(pixels, dither="threshold")
    assert np.array_equal(exposure > 0.5, pixels / 255.0 <= 0.5)


def test_white_runs_are_travel_and_burnt_pixels_are_reached_through_the_overscan() -> None:
    pixels = np.full((10, 400), 255, dtype=np.uint8)
    pixels[:, 20:40] = 0
    pixels[:, 360:380] = 0  # 32 mm of white between: crossed with G0
    gcode, exposure = _engrave(pixels, overscan=3.0)
    assert np.abs(exposure - (1.0 - pixels / 255.0)).max() < 1e-6
    rows = gcode.split("; layer")[1].splitlines()
    assert sum(1 for line in rows if line.startswith("G0")) == 2 * 10  # into each line, across
    longest_off = max(_moves_off(gcode))
    assert longest_off <= 3.0 + 1e-6


def _moves_off(gcode: str) -> list[float]:
    """The lengths of the G1 S0 moves along X (the overscan, short white runs)."""
    lengths, x, s = [], 0.0, 0
    for line in gcode.splitlines():
        found = dict(re.findall(r"([XSG])(-?[\d.]+)", line))
        s = int(found.get("S", s))
        new_x = float(found.get("X", x))
        if found.get("G") == "1" and s == 0:
            lengths.append(abs(new_x - x))
        x = new_x
    return lengths


def test_an_image_is_sized_by_its_dpi_or_by_the_width_given() -> None:
    pixels = _photo(300, 150)
    assert read_drawing(_png(pixels, dpi=300), "a.png").width_mm == pytest.approx(25.4, rel=1e-4)
    given = read_drawing(_png(pixels), "a.png", width_mm=60.0)
    assert (given.width_mm, given.height_mm) == pytest.approx((60.0, 30.0))


def test_the_estimate_of_an_engrave_equals_its_simulated_run() -> None:
    from server.offline.estimate import estimate, execute

    pixels = _photo(100, 50)  # 10 x 5 mm
    drawing = read_drawing(_png(pixels), "photo.png")
    layer = drawing.layers[0]
    layer.settings = layer_settings({"interval": 0.2, "speed": 6000, "dither": "jarvis"},
                                    layer.settings)
    lines = make_job(drawing).splitlines()
    core = make_config().core.model_copy(deep=True)
    core.machine.soft_limits = False  # the overscan starts left of zero
    planned, run = estimate(lines, core).duration_s, execute(lines, core).duration_s
    assert run > 2.0 and abs(planned - run) <= 0.01 * run, (planned, run)
