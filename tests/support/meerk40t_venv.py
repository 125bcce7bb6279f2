"""MeerK40t, the reference CAM the drawing import is compared with, in its own virtual
environment (it is a desktop program with its own dependencies): ``build/meerk40t-venv``, or
``MOTIOND_MEERK40T_VENV``. ``.ci/run`` builds it at install time with
``python3 -m tests.support.meerk40t_venv``; the test builds it when absent. It runs without
its GUI (``-Z``), with ``HOME`` pointed at a scratch folder: it writes its settings there."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

VERSION = "0.9.9100"
REPO = Path(__file__).resolve().parents[2]
VENV = Path(os.environ.get("MOTIOND_MEERK40T_VENV", REPO / "build" / "meerk40t-venv"))


def ensure_meerk40t() -> Path:
    """The ``meerk40t`` program, installed in its own environment the first time."""
    marker = VENV / f".meerk40t-{VERSION}"
    if not marker.exists():
        subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
        subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", f"meerk40t=={VERSION}",
                        "pillow", "numpy"], check=True)
        marker.touch()
    return VENV / "bin" / "meerk40t"


def meerk40t_gcode(svg: Path, out: Path, home: Path) -> str:
    """MeerK40t's G-code for ``svg`` on its generic Grbl device, every element in one engrave
    (line) operation at its defaults, planned and optimised as its GUI would."""
    commands = ["service device start -i grbl 0", "operation* delete", "element* engrave",
                "plan copy preprocess validate blob preopt optimize", f"plan save_job {out}",
                "quit"]
    argv = [str(ensure_meerk40t()), "-Z", "-X", "-A", str(svg)]
    for command in commands:
        argv += ["-e", command]
    home.mkdir(parents=True, exist_ok=True)
    subprocess.run(argv, env={**os.environ, "HOME": str(home)}, check=True,
                   capture_output=True, timeout=120)
    return out.read_text()


if __name__ == "__main__":
    print(ensure_meerk40t())
