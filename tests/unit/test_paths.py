"""Where motiond keeps its files: XDG folders, a data folder per server, the config search."""

from __future__ import annotations

from pathlib import Path

import pytest

from server import paths
from server.config_loader import build_config
from tests.conftest import HOME, make_config


def default_machine(data_dir: Path | None = None) -> object:
    """The default machine's config as ``motiond`` builds it without a file (no path)."""
    data = {"axes": {"x": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000,
                           "max_mm": 100}}}
    if data_dir is not None:
        data["jobs"] = {"data_dir": str(data_dir)}  # type: ignore[dict-item]
    return build_config(data)


def test_the_data_folder_follows_xdg_data_home(monkeypatch: pytest.MonkeyPatch,
                                               tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    config = default_machine()
    assert paths.data_dir(config.core) == tmp_path / "xdg" / "motiond"  # type: ignore[attr-defined]
    assert paths.jobs_dir(config.core) == tmp_path / "xdg" / "motiond" / "jobs"  # type: ignore[attr-defined]


def test_the_suite_runs_with_a_stand_in_home() -> None:
    assert Path.home() == HOME
    assert paths.data_dir(default_machine().core).is_relative_to(HOME)  # type: ignore[attr-defined]


def test_a_configured_data_folder_holds_jobs_and_settings_apart(tmp_path: Path) -> None:
    config = default_machine(tmp_path / "data")
    assert paths.jobs_dir(config.core) == tmp_path / "data" / "jobs"  # type: ignore[attr-defined]
    assert paths.settings_path(config) == tmp_path / "data" / "settings.toml"  # type: ignore[arg-type]


def test_a_configured_jobs_folder_is_used_as_is_with_the_home_expanded() -> None:
    config = make_config(jobs={"jobs_dir": "~/printer_data/gcodes"})
    assert paths.jobs_dir(config.core) == HOME / "printer_data" / "gcodes"


def test_settings_of_a_config_file_live_beside_it(tmp_path: Path) -> None:
    config = make_config()
    config = type(config)(config.core, config.modules, tmp_path / "laser.toml")
    assert paths.settings_path(config) == tmp_path / "laser.settings.toml"


def test_hidden_settings_among_the_job_files_move_out_once(tmp_path: Path) -> None:
    (tmp_path / ".settings.toml").write_text("x = 1\n")
    config = default_machine(tmp_path)
    assert paths.settings_path(config).read_text() == "x = 1\n"  # type: ignore[arg-type]
    assert not (tmp_path / ".settings.toml").exists()


def test_the_config_search_path_is_here_then_the_users_then_the_systems(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    monkeypatch.chdir(tmp_path)
    assert paths.config_search_path() == [
        tmp_path / "motiond.toml", tmp_path / "config" / "motiond" / "motiond.toml",
        Path("/etc/motiond/motiond.toml")]
    assert paths.find_config() is None or paths.find_config() == Path("/etc/motiond/motiond.toml")
    user = tmp_path / "config" / "motiond" / "motiond.toml"
    user.parent.mkdir(parents=True)
    user.write_text("")
    assert paths.find_config() == user
    (tmp_path / "motiond.toml").write_text("")
    assert paths.find_config() == tmp_path / "motiond.toml"
