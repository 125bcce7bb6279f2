"""The material library: layer settings by name, validated in and out, applied by layer."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.cam.job import read_drawing
from server.cam.materials import apply_material, dump_library, parse_library, with_material
from server.errors import DrawingError

DATA = Path(__file__).parents[1] / "data" / "cam"


def test_a_material_round_trips_with_full_names_and_applies_by_layer() -> None:
    library = with_material({}, "3 mm plywood", {"#ff0000": {"speed": 600, "passes": 2},
                                                 "#0000ff": {"mode": "fill", "power": 30}})
    assert library["3 mm plywood"]["#ff0000"] == {"speed_mm_min": 600.0, "passes": 2}
    assert parse_library(dump_library(library)) == library
    drawing = read_drawing((DATA / "three-colours.svg").read_bytes(), "three-colours.svg")
    apply_material(drawing, library, "3 mm plywood")
    red, blue, green = (drawing.layer(n).settings for n in ("#ff0000", "#0000ff", "#008000"))
    assert (red.speed_mm_min, red.passes, red.mode) == (600.0, 2, "line")
    assert (blue.power_pct, blue.mode) == (30.0, "fill")
    assert green.power_pct == 50.0, "a layer the material does not name keeps its settings"


@pytest.mark.parametrize(("name", "layers", "message"), [
    ("wood", {"#ff0000": {"power": 120}}, "material 'wood', layer #ff0000: power_pct"),
    ("wood", {"#ff0000": {"depth": 1}}, "depth: Extra inputs are not permitted"),
    ("", {}, "a name of 1 to 100 characters"),
    ("wood", {"#ff0000": 5}, "settings must be an object"),
])
def test_a_bad_material_is_refused_naming_it(name: str, layers: object, message: str) -> None:
    with pytest.raises(DrawingError, match=message):
        with_material({}, name, layers)


def test_a_damaged_library_file_and_an_unknown_material_are_named() -> None:
    with pytest.raises(DrawingError, match="materials.json: not JSON"):
        parse_library("{", "materials.json")
    drawing = read_drawing((DATA / "settings.svg").read_bytes(), "settings.svg")
    with pytest.raises(DrawingError, match=r"no material 'oak' \(materials: wood\)"):
        apply_material(drawing, with_material({}, "wood", {}), "oak")
