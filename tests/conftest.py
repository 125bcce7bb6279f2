"""Shared fixtures: configs built from dicts, the corpus folder, the firmware rigs, a virtual
Klipper MCU, and a stand-in home folder, so no test reads or writes the user's."""

from __future__ import annotations

import copy
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from server.config import Config
from server.config_loader import build_config

if TYPE_CHECKING:
    from tests.support.virtual_mcu import VirtualMcu

REPO = Path(__file__).resolve().parent.parent
CORPUS = REPO / "tests" / "data" / "corpus"  # real G-code files, sources in SOURCES.md

BASE: dict[str, Any] = {
    "axes": {
        "x": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000, "max_mm": 400},
        "y": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000, "max_mm": 300},
        "z": {"steps_per_mm": 400, "max_rate_mm_s": 10, "accel_mm_s2": 200,
              "min_mm": -50, "max_mm": 50},
    },
    "tcp": {"port": 0},
    "http": {"port": 0},
}


# Every data directory of a run lives under one folder, removed when the run ends.
DATA_ROOT = Path(tempfile.mkdtemp(prefix="motiond-tests-"))
# The user's home and XDG folders point into it for the whole run (server processes inherit
# them): a server a test started without a data folder of its own would use these, and the run
# fails at its end (below) instead of reading or changing the user's settings and jobs.
HOME = DATA_ROOT / "home"
HOME_VARIABLES = {
    "HOME": HOME, "XDG_DATA_HOME": HOME / ".local" / "share",
    "XDG_CONFIG_HOME": HOME / ".config", "XDG_STATE_HOME": HOME / ".local" / "state",
    "XDG_CACHE_HOME": HOME / ".cache",
}
for _name, _folder in HOME_VARIABLES.items():
    _folder.mkdir(parents=True, exist_ok=True)
    os.environ[_name] = str(_folder)
os.environ.pop("MOTIOND_DATA_DIR", None)
os.environ.pop("MOTIOND_CONFIG", None)


def motiond_files_in_home() -> list[Path]:
    """What some test's server wrote to the stand-in home: motiond's own folders."""
    return sorted(path for path in HOME.rglob("*") if path.name == "motiond")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The fast tier (``pytest -m "not slow"``, a developer's loop after each change) leaves
    out every end-to-end test (processes, browsers, brokers, firmware rigs) and the in-process
    tests marked ``slow`` (seconds each: whole corpus files, real-time holds)."""
    for item in items:
        if "e2e" in item.path.parts:
            item.add_marker(pytest.mark.slow)


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    stray = motiond_files_in_home()
    shutil.rmtree(DATA_ROOT, ignore_errors=True)
    if stray:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
        print(f"\nFAILED: a test's server used the home folder instead of its own: {stray}")


def make_config(extra: dict[str, Any] | None = None, **sections: Any) -> Config:
    """A small XYZ machine, with extra sections merged in; its data directory is a fresh
    temporary folder, so tests never read or write the user's settings and jobs."""
    data = copy.deepcopy(BASE)
    data["jobs"] = {"data_dir": tempfile.mkdtemp(prefix="data-", dir=DATA_ROOT)}
    for key, value in {**(extra or {}), **sections}.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key].update(value)
        else:
            data[key] = value
    return build_config(data, "test.toml")


@pytest.fixture
def config() -> Config:
    return make_config()


@pytest.fixture
def mcu() -> Iterator[VirtualMcu]:
    """A virtual Klipper MCU on a pty (a test file may define its own, with other options)."""
    from tests.support.virtual_mcu import VirtualMcu

    virtual = VirtualMcu().start()
    yield virtual
    virtual.stop()
