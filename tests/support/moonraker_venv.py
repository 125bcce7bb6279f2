"""Moonraker's own virtual environment (it pins its dependencies): ``build/moonraker-venv``,
or ``MOTIOND_MOONRAKER_VENV``. ``.ci/run`` builds it at install time with
``python3 -m tests.support.moonraker_venv``; the test fixture builds it when absent."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

VERSION = "0.11.0"
REPO = Path(__file__).resolve().parents[2]
VENV = Path(os.environ.get("MOTIOND_MOONRAKER_VENV", REPO / "build" / "moonraker-venv"))


def ensure_moonraker() -> Path:
    """The ``moonraker`` program, installed in its own environment the first time."""
    marker = VENV / f".moonraker-{VERSION}"
    if not marker.exists():
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
        subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", f"moonraker=={VERSION}"],
                       check=True)
        marker.touch()
    return VENV / "bin" / "moonraker"


if __name__ == "__main__":
    print(ensure_moonraker())
