"""Shared fixtures: configs built from dicts, and the corpus folder."""

from __future__ import annotations

import copy
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import pytest

from server.config import Config
from server.config_loader import build_config

REPO = Path(__file__).resolve().parent.parent
CORPUS = Path(os.environ.get("MOTIOND_CORPUS", REPO.parent / "shared" / "corpus"))
if not CORPUS.is_dir():  # a checkout with shared/ beside it (CI) or inside the repo's parent
    CORPUS = REPO / ".." / "shared" / "corpus"

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


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    shutil.rmtree(DATA_ROOT, ignore_errors=True)


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
