"""``motiond import``: a drawing into a G-code file with each layer's settings from
``--layer``, the laser's maximum S from the machine's config, clear refusals, and a named
extra when the parsers are missing."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

from server.cli import main
from tests.integration.test_cli_fit import default_config

DATA = Path(__file__).parents[1] / "data" / "cam"


def test_import_writes_each_layer_with_its_settings(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "coaster.gcode"
    status = main(["import", str(DATA / "three-colours.svg"), "-o", str(out),
                   "--config", str(default_config(tmp_path)),
                   "--layer", "#0000ff:power=40,speed=6000,angle=45,interval=0.2",
                   "--layer", "#ff0000:passes=2,power=90"])
    assert status == 0
    gcode = out.read_text()
    blue = gcode.split("; layer #0000ff")[1].split("; layer")[0]
    assert " S400" in blue and "F6000" in blue and "fill, 6000 mm/min, 40 %" in blue
    assert gcode.count("; layer #ff0000") == 2 and " S900" in gcode
    assert gcode.rstrip().endswith("M5 S0")
    listed = capsys.readouterr().err
    assert "#0000ff  fill" in listed and f"wrote {out}" in listed


def test_power_is_scaled_to_the_lasers_maximum_s(tmp_path: Path, capsys: Any) -> None:
    config = default_config(tmp_path)
    config.write_text(config.read_text().replace("maximum_s_value = 1000",
                                                 "maximum_s_value = 255"))
    out = tmp_path / "gear.gcode"
    assert main(["import", str(DATA / "settings.svg"), "-o", str(out), "--config", str(config),
                 "--layer", "#000000:power=100", "--json"]) == 0
    assert " S255 " in out.read_text()
    described = json.loads(capsys.readouterr().out)
    assert described["drawing"]["layers"][0]["settings"]["power_pct"] == 100.0


@pytest.mark.parametrize(("option", "message"), [
    ("#123456:power=50", "no layer '#123456' (layers: #0000ff, #008000, #ff0000)"),
    ("#ff0000:power=150", "layer #ff0000: power_pct: Input should be less than or equal to 100"),
    ("#ff0000:colour=red", "layer #ff0000: colour: Extra inputs are not permitted"),
    ("#ff0000", "give NAME:key=value"),
])
def test_a_bad_layer_option_is_refused_naming_it(tmp_path: Path, capsys: Any, option: str,
                                                 message: str) -> None:
    out = tmp_path / "x.gcode"
    assert main(["import", str(DATA / "three-colours.svg"), "-o", str(out),
                 "--config", str(default_config(tmp_path)), "--layer", option]) == 1
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_a_missing_extra_is_named(tmp_path: Path, capsys: Any,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ezdxf", None)  # as if not installed
    assert main(["import", str(DATA / "bracket.dxf"), "-o", str(tmp_path / "b.gcode"),
                 "--config", str(default_config(tmp_path))]) == 2
    assert "needs ezdxf: pip install 'motiond[cam]'" in capsys.readouterr().err


def test_a_material_from_the_machines_library_applies_before_layer_options(
        tmp_path: Path) -> None:
    (tmp_path / "materials.json").write_text(json.dumps({"materials": {"plywood": {
        "#ff0000": {"power_pct": 90, "passes": 3}, "#0000ff": {"power_pct": 20}}}}))
    out = tmp_path / "coaster.gcode"
    assert main(["import", str(DATA / "three-colours.svg"), "-o", str(out),
                 "--config", str(default_config(tmp_path)), "--material", "plywood",
                 "--layer", "#ff0000:passes=1"]) == 0
    gcode = out.read_text()
    assert gcode.count("; layer #ff0000") == 1 and " S900" in gcode and " S200" in gcode


def test_order_puts_the_layers_named_first(tmp_path: Path) -> None:
    out = tmp_path / "coaster.gcode"
    assert main(["import", str(DATA / "three-colours.svg"), "-o", str(out),
                 "--config", str(default_config(tmp_path)), "--order", "#ff0000,#008000"]) == 0
    headers = [line.split()[2] for line in out.read_text().splitlines()
               if line.startswith("; layer")]
    assert headers == ["#ff0000:", "#008000:", "#0000ff:"]
    assert main(["import", str(DATA / "three-colours.svg"), "-o", str(out),
                 "--order", "#123456", "--config", str(default_config(tmp_path))]) == 1
