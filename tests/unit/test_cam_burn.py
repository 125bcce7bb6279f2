"""A burn that equals the drawing: real SVG and DXF files (tests/data/cam, SOURCES.md) made
into jobs, run through the machine's planner, and what the laser burnt compared with the
drawing as resvg renders it, at 0.1 mm per pixel, layer by layer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import shapely

from server.cam.job import make_job, read_drawing
from server.cam.model import layer_settings
from server.offline.estimate import estimate, execute
from tests.conftest import make_config
from tests.support.burn import burn, burn_mask, colour_mask, iou, render

DATA = Path(__file__).parents[1] / "data" / "cam"
KERF_MM = 1.0  # the tabler icons' lines are drawn this wide in the reference (0.25 units)


def _job(name: str, **settings: object) -> tuple[bytes, str, object]:
    data = (DATA / name).read_bytes()
    drawing = read_drawing(data, name)
    for layer in drawing.layers:
        layer.settings = layer_settings(dict(settings), layer.settings)
    return data, make_job(drawing), drawing


@pytest.mark.parametrize("name", ["air-balloon.svg", "settings.svg"])
def test_a_line_drawing_burns_what_the_reference_renderer_draws(name: str) -> None:
    data, gcode, drawing = _job(name)
    burnt = burn(gcode, make_config())
    reference = render(data.replace(b'stroke-width="2"', b'stroke-width="0.25"'), 96, 96)
    score = iou(burn_mask(burnt.segments, 96, 96, KERF_MM), reference[..., 3] > 127)
    assert score >= 0.97, f"{name}: IoU {score:.4f}"


def test_a_filled_drawing_burns_its_area() -> None:
    data, gcode, _ = _job("award.svg", interval_mm=0.1)
    burnt = burn(gcode, make_config())
    reference = render(data, 96, 96)[..., 3] > 127
    score = iou(burn_mask(burnt.segments, 96, 96, 0.1, cap="butt"), reference)
    assert score >= 0.97, f"IoU {score:.4f}"


def test_three_colour_drawing_burns_each_layer_in_its_mode() -> None:
    data = (DATA / "three-colours.svg").read_bytes()
    drawing = read_drawing(data, "three-colours.svg")
    assert [(layer.name, layer.settings.mode) for layer in drawing.layers] == [
        ("#0000ff", "fill"), ("#008000", "line"), ("#ff0000", "line")]  # the outline last
    reference = render(data, 120, 90)
    colours = [layer.name for layer in drawing.layers]
    for layer in drawing.layers:
        others = [other for other in drawing.layers if other is not layer]
        for other in others:
            other.settings = other.settings.model_copy(update={"enabled": False})
        layer.settings = layer.settings.model_copy(update={"enabled": True})
        burnt = burn(make_job(drawing), make_config())
        fill = layer.settings.mode == "fill"
        mask = burn_mask(burnt.segments, 120, 90, 0.1 if fill else 0.8,
                         cap="butt" if fill else "round")
        score = iou(mask, colour_mask(reference, layer.name, colours))
        assert score >= 0.97, f"layer {layer.name}: IoU {score:.4f}"


def test_a_dxf_burns_what_the_same_geometry_drawn_as_svg_shows() -> None:
    data, gcode, drawing = _job("bracket.dxf")
    assert (drawing.width_mm, drawing.height_mm) == pytest.approx((80.0, 50.0), abs=1e-6)
    burnt = burn(gcode, make_config())
    reference = render((DATA / "bracket_reference.svg").read_bytes(), 80, 50)[..., 3] > 127
    score = iou(burn_mask(burnt.segments, 80, 50, 0.8), reference)
    assert score >= 0.97, f"IoU {score:.4f}"


def _cut_polylines(gcode: str) -> list[np.ndarray]:
    """The job's cuts, one polyline per run of G1 between two G0."""
    runs: list[list[tuple[float, float]]] = []
    x = y = 0.0
    for line in gcode.splitlines():
        words = dict((w[0], w[1:]) for w in line.split() if w[0] in "GXY")
        x, y = float(words.get("X", x)), float(words.get("Y", y))
        if words.get("G") == "0":
            runs.append([(x, y)])
        elif words.get("G") == "1" and runs:
            runs[-1].append((x, y))
    return [np.array(run) for run in runs if len(run) > 1]


@pytest.mark.parametrize("name", ["air-balloon.svg", "settings.svg", "three-colours.svg",
                                  "bracket.dxf"])
def test_no_contour_is_cut_before_a_shape_inside_it_in_any_layer(name: str) -> None:
    _, gcode, _ = _job(name)
    runs = _cut_polylines(gcode)
    for index, outer in enumerate(runs):
        if len(outer) < 4 or not np.allclose(outer[0], outer[-1], atol=1e-3):
            continue
        polygon = shapely.Polygon(outer)
        later = [run for run in runs[index + 1:] if polygon.contains(shapely.LineString(run))]
        assert not later, f"{name}: contour {index} cut before {len(later)} shape(s) inside it"


def test_passes_follow_each_other_and_layers_keep_their_order() -> None:
    _, gcode, _ = _job("three-colours.svg", passes=2)
    headers = [line for line in gcode.splitlines() if line.startswith("; layer")]
    assert [h.split()[2].rstrip(":") + h.split()[-3] for h in headers] == [
        "#0000ff1", "#0000ff2", "#0080001", "#0080002", "#ff00001", "#ff00002"]


def test_the_estimate_of_a_generated_job_equals_its_simulated_run() -> None:
    _, gcode, _ = _job("settings.svg", speed_mm_min=6000)
    core = make_config().core
    planned = estimate(gcode.splitlines(), core).duration_s
    run = execute(gcode.splitlines(), core).duration_s
    assert run > 1.0
    assert abs(planned - run) <= 0.01 * run, (planned, run)


OVERLAPS = b"""<svg xmlns="http://www.w3.org/2000/svg" width="80mm" height="40mm"
  viewBox="0 0 80 40">
  <circle cx="20" cy="20" r="12" fill="#000"/>
  <circle cx="32" cy="20" r="12" fill="#000"/>
  <path fill="#000" d="M48 6 h10 v28 h-10 z M50 10 h6 v8 h-6 z"/>
  <path fill="#000" fill-rule="evenodd" d="M64 6 h10 v28 h-10 z M66 22 h6 v8 h-6 z"/>
</svg>"""


def test_overlapping_fills_unite_and_each_path_keeps_its_fill_rule() -> None:
    drawing = read_drawing(OVERLAPS, "overlaps.svg")
    burnt = burn(make_job(drawing), make_config())
    score = iou(burn_mask(burnt.segments, 80, 40, 0.1, cap="butt"),
                render(OVERLAPS, 80, 40)[..., 3] > 127)
    assert score >= 0.97, f"IoU {score:.4f}"
