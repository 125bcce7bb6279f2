"""A misspelt config key or section is refused with the name it was probably meant to be."""

from __future__ import annotations

from typing import Any

import pytest

from server.config_loader import build_config
from server.errors import ConfigError

AXES = {"x": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000, "max_mm": 100}}


def problems(data: dict[str, Any]) -> list[str]:
    with pytest.raises(ConfigError) as refused:
        build_config({"axes": AXES, **data}, "my.toml")
    return refused.value.problems


def test_a_misspelt_core_key_names_the_key_it_resembles() -> None:
    assert problems({"planner": {"junction_deviaton_mm": 0.01}}) == [
        "my.toml: [planner] junction_deviaton_mm: unknown key "
        "(did you mean junction_deviation_mm?)"]


def test_a_misspelt_axis_key_inside_a_named_table_names_the_key() -> None:
    found = problems({"axes": {"x": {**AXES["x"], "max_rate_mm_min": 500}}})
    assert found == ["my.toml: [axes.x] max_rate_mm_min: unknown key "
                     "(did you mean max_rate_mm_s?)"]


def test_a_misspelt_module_key_names_the_key() -> None:
    found = problems({"laser": {"pin": "laser", "pwm_frequency_hzz": 1000}})
    assert found == ["my.toml: [laser] pwm_frequency_hzz: unknown key "
                     "(did you mean pwm_frequency_hz?)"]


def test_a_misspelt_section_names_the_section_it_resembles() -> None:
    found = problems({"lazer": {"pin": "laser"}})
    assert found[0].startswith("my.toml: [lazer]: unknown section (did you mean [laser]?)")


def test_a_key_like_nothing_known_gets_no_guess() -> None:
    found = problems({"planner": {"zzzz": 1}})
    assert found == ["my.toml: [planner] zzzz: unknown key"]
