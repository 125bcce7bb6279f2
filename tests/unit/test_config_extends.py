"""A config file extends the built-in machine: what it names replaces the default's, the rest
stays, and ``check-config`` says where each value came from."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.cli import main
from server.config_loader import load_config
from tests.conftest import REPO


def _file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "motiond.toml"
    path.write_text(text)
    return path


def test_a_one_line_trusted_clients_file_is_a_whole_config(tmp_path: Path) -> None:
    # one line of TOML (a dotted key: a [table] header must end its line)
    config = load_config(_file(tmp_path, 'protocol.trusted_clients = ["192.168.1.0/24"]\n'))
    assert config.core.protocol.trusted_clients == ["192.168.1.0/24"]
    default = load_config()
    assert config.core.axes == default.core.axes  # the built-in machine stays
    assert [spec.section for spec in config.modules] == [s.section for s in default.modules]
    assert config.core.protocol.line_limit == default.core.protocol.line_limit


def test_a_key_replaces_the_defaults_and_its_sections_other_keys_stay(tmp_path: Path) -> None:
    config = load_config(_file(tmp_path, '[http]\nallowed_hosts = ["laser.local"]\n'
                                         '[laser]\nmaximum_s_value = 255\n'
                                         '[switch.fan]\npin = "fan"\non_mcode = 106\n'
                                         'off_mcode = 107\n'))
    assert config.core.http.allowed_hosts == ["laser.local"]
    assert config.core.http.port == 8080
    laser = next(spec.config for spec in config.modules if spec.section == "laser")
    assert laser.maximum_s_value == 255 and laser.pin == "laser"  # type: ignore[attr-defined]
    assert {"switch.air", "switch.fan"} <= {spec.section for spec in config.modules}


def test_a_file_that_names_its_axes_is_a_machine_of_its_own() -> None:
    config = load_config(REPO / "examples" / "cnc.toml")
    assert "laser" not in {spec.section for spec in config.modules}
    assert config.core.axis_names == ("X", "Y", "Z")
    two_axes = load_config(REPO / "examples" / "mqtt.toml")
    assert two_axes.core.axis_names == ("X", "Y")  # no built-in Z inherited


def test_check_config_shows_the_merged_machine_and_where_each_value_came_from(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _file(tmp_path, '[protocol]\ntrusted_clients = ["192.168.1.0/24", "10.0.0.5"]\n'
                           'token = "a-secret-token"\n')
    assert main(["check-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert "extends the built-in machine" in out
    assert f'trusted_clients = ["192.168.1.0/24", "10.0.0.5"]  # {path}' in out
    assert 'name = "laser-400x300 (simulated)"  # <default config>' in out
    assert "line_limit = 256  # default" in out
    assert "192.168.1.0/24 (256 addresses), 10.0.0.5/32 (1 address)" in out
    assert "a-secret-token" not in out and 'token = "<set>"' in out


def test_the_pi_guides_three_line_config_is_enough(tmp_path: Path) -> None:
    guide = (REPO / "docs" / "install.md").read_text()
    text = guide.split("<<'TOML'\n", 1)[1].split("   TOML\n", 1)[0]
    config = load_config(_file(tmp_path, "\n".join(line.strip() for line in text.splitlines())))
    assert (config.core.tcp.host, config.core.http.host) == ("0.0.0.0", "0.0.0.0")
    assert config.core.http.also_allowed_hosts == ["laser.local"]
    assert config.core.http.allowed_hosts is None  # the local names stay allowed
