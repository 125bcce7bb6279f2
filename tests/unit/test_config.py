"""Config loading and every kind of config error: each names the file, section and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.cli import main
from server.config_loader import build_config, load_config
from server.errors import ConfigError
from tests.conftest import BASE, REPO, make_config


def problems_of(data: dict, label: str = "m.toml") -> list[str]:
    with pytest.raises(ConfigError) as info:
        build_config(data, label)
    return info.value.problems


def test_embedded_default_is_a_simulated_laser_cutter() -> None:
    config = load_config()
    assert config.core.backend.kind == "sim"
    assert config.core.machine.laser_mode
    assert config.core.axis_names == ("X", "Y", "Z")


@pytest.mark.parametrize(
    "name",
    ["laser.toml", "cnc.toml", "plotter.toml", "mqtt.toml", "grbl-link.toml", "klipper-laser.toml"],
)
def test_example_configs_load(name: str) -> None:
    config = load_config(REPO / "examples" / name)
    assert config.core.axis_names[:2] == ("X", "Y")
    assert config.path == REPO / "examples" / name


def test_a_klipper_backend_needs_a_serial_path_and_the_pins_of_every_axis() -> None:
    pins = {"step_pin": "PB13", "dir_pin": "!PB12"}
    assert problems_of({**BASE, "backend": {"kind": "klipper", "axes": {"x": pins}}})[0].endswith(
        'kind = "klipper" needs serial (the MCU\'s device path)')
    problems = problems_of({**BASE, "backend": {"kind": "klipper", "serial": "/dev/ttyACM0",
                                                "axes": {"x": pins}}})
    assert "[backend.axes.*] must give the pins of every axis" in problems[0]
    bad_pin = {"step_pin": "PB 13", "dir_pin": "PB12"}
    problems = problems_of({**BASE, "backend": {"kind": "klipper", "serial": "/dev/ttyACM0",
                                                "axes": {"x": bad_pin}}})
    assert any("[backend.axes.x] step_pin" in p for p in problems)


def test_unknown_key_names_file_section_and_key() -> None:
    data = {**BASE, "planner": {"junction_deviaton_mm": 0.1}}
    assert problems_of(data) == ["m.toml: [planner] junction_deviaton_mm: unknown key "
                                 "(did you mean junction_deviation_mm?)"]


def test_wrong_type_names_the_value() -> None:
    data = {**BASE, "stepgen": {"tick_hz": "fast"}}
    (problem,) = problems_of(data)
    assert problem.startswith("m.toml: [stepgen] tick_hz: ")
    assert "'fast'" in problem


def test_out_of_range_value() -> None:
    axes = {**BASE["axes"], "x": {**BASE["axes"]["x"], "accel_mm_s2": -5}}
    (problem,) = problems_of({**BASE, "axes": axes})
    assert problem.startswith("m.toml: [axes.x] accel_mm_s2: ")
    assert "greater than 0" in problem


def test_missing_required_value_and_section() -> None:
    axes = {"x": {"steps_per_mm": 80, "max_rate_mm_s": 5, "accel_mm_s2": 5}}
    assert problems_of({"axes": axes}) == ["m.toml: [axes.x] max_mm: missing required value"]
    assert problems_of({}) == ["m.toml: [axes]: missing required value"]


def test_unknown_section_lists_the_known_ones() -> None:
    (problem,) = problems_of({**BASE, "lazer": {}})
    assert problem.startswith("m.toml: [lazer]: unknown section (did you mean [laser]?) (known: ")
    assert "heartbeat" in problem


def test_every_problem_is_reported_not_just_the_first() -> None:
    data = {**BASE, "planner": {"bogus": 1}, "tcp": {"port": 99999}, "nope": {}}
    assert len(problems_of(data)) == 3


def test_module_section_is_validated_by_the_module_model() -> None:
    assert problems_of({**BASE, "heartbeat": {"log_every_s": -1}})[0].startswith(
        "m.toml: [heartbeat] log_every_s: ")
    assert problems_of({**BASE, "heartbeat": {"colour": "red"}}) == [
        "m.toml: [heartbeat] colour: unknown key"]


def test_bad_axis_name_and_empty_travel() -> None:
    axes = {"q": {**BASE["axes"]["x"]}}
    assert "axis names must be among" in problems_of({"axes": axes})[0]
    axes = {"x": {**BASE["axes"]["x"], "min_mm": 10, "max_mm": 5}}
    assert problems_of({"axes": axes}) == ["m.toml: [axes.x]: max_mm must be greater than min_mm"]


def test_invalid_toml_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[axes\n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.toml")


def test_check_config_prints_every_problem_and_exits_non_zero(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "m.toml"
    bad.write_text((REPO / "examples" / "cnc.toml").read_text() + "\n[spindel]\n")
    assert main(["check-config", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}: [spindel]: unknown section" in err
    assert "1 problem(s)" in err
    assert main(["check-config", str(REPO / "examples" / "cnc.toml")]) == 0


def test_serve_refuses_a_bad_config_without_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "m.toml"
    bad.write_text("[axes.x]\nsteps_per_mm = 0\n")
    assert main(["--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "[axes.x] steps_per_mm" in err and "refusing to start" in err


def test_make_config_helper_builds_from_dicts() -> None:
    assert make_config(planner={"max_blocks": 16}).core.planner.max_blocks == 16


def test_grbl_backend_options_are_checked_with_file_section_and_key() -> None:
    axes = {"x": {"steps_per_mm": 80, "max_rate_mm_s": 100, "accel_mm_s2": 100, "max_mm": 100}}
    cases = [
        ({"kind": "grbl"}, 'm.toml: [backend]: kind = "grbl" needs exactly one of serial'),
        ({"kind": "grbl", "serial": "/dev/ttyUSB0", "status_hz": 50},
         "m.toml: [backend] status_hz: Input should be less than or equal to 20"),
        ({"kind": "grbl", "tcp": "fluidnc.local"}, "m.toml: [backend] tcp: String should match"),
        ({"kind": "sim", "serial": "/dev/ttyUSB0"}, 'serial and tcp are options of kind = "grbl"'),
    ]
    for backend, expected in cases:
        with pytest.raises(ConfigError) as raised:
            build_config({"axes": axes, "backend": backend}, "m.toml")
        assert expected in str(raised.value), str(raised.value)
    with pytest.raises(ConfigError, match="cannot also be served"):
        build_config({"axes": axes, "backend": {"kind": "grbl", "serial": "/dev/ttyACM0"},
                      "serial": {"device": "/dev/ttyACM0"}}, "m.toml")


def test_backend_links_belong_to_their_kind_and_baud_defaults_by_kind() -> None:
    pins = {"x": {"step_pin": "PB13", "dir_pin": "!PB12"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2"}, "z": {"step_pin": "PC1", "dir_pin": "PC2"}}
    klipper = {"kind": "klipper", "serial": "/dev/ttyACM0", "axes": pins}
    assert build_config({**BASE, "backend": klipper}, "m.toml").core.backend.baud == 250_000
    grbl = {"kind": "grbl", "serial": "/dev/ttyUSB0"}
    assert build_config({**BASE, "backend": grbl}, "m.toml").core.backend.baud == 115_200
    assert problems_of({**BASE, "backend": {**klipper, "tcp": "mcu:23"}})[0].endswith(
        'tcp is an option of kind = "grbl"; a Klipper MCU is on serial')
    assert problems_of({**BASE, "backend": {"serial": "/dev/ttyUSB0"}})[0].endswith(
        'serial and tcp are options of kind = "grbl" or "klipper"')
