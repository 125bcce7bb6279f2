"""The same drawing through MeerK40t (its own environment, no GUI) as the reference CAM: the
total length cut within 1 %, the same closed shapes, and the time each job takes on our
planner side by side."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from server.cam.job import make_job, read_drawing
from server.cam.model import layer_settings
from server.offline.estimate import estimate
from tests.conftest import make_config
from tests.support.meerk40t import meerk40t_gcode

DATA = Path(__file__).parents[1] / "data" / "cam"
WORD = re.compile(r"([GMXYSF])(-?\d+(?:\.\d*)?)")


def cuts(gcode: str) -> list[np.ndarray]:
    """The runs the laser cuts (G1 with S > 0), split where it travels or turns off. Commands
    are split at each G or M word: MeerK40t writes several on one line."""
    runs: list[list[tuple[float, float]]] = []
    x = y = s = 0.0
    motion, cutting = 0, False
    for command in re.split(r"(?=[GM]\d)", gcode):
        words = dict(WORD.findall(command))
        if words.get("G") in ("0", "1"):
            motion = int(words["G"])
        s = float(words.get("S", s))
        if "X" not in words and "Y" not in words:
            continue
        start = (x, y)
        x, y = float(words.get("X", x)), float(words.get("Y", y))
        on = motion == 1 and s > 0
        if on and not cutting:
            runs.append([start])
        if on:
            runs[-1].append((x, y))
        cutting = on
    return [np.array(_unique(run)) for run in runs if len(run) > 1]


def _unique(run: list[tuple[float, float]]) -> list[tuple[float, float]]:
    kept = [run[0]]
    for point in run[1:]:
        if point != kept[-1]:
            kept.append(point)
    return kept


def _length(runs: list[np.ndarray]) -> float:
    return float(sum(np.hypot(*np.diff(run, axis=0).T).sum() for run in runs))


def _closed(runs: list[np.ndarray]) -> int:
    return sum(1 for run in runs if len(run) > 3 and math.dist(run[0], run[-1]) < 0.05)


@pytest.mark.parametrize("name", ["settings.svg", "air-balloon.svg", "three-colours.svg"])
def test_meerk40t_cuts_the_same_length_and_closed_shapes(name: str, tmp_path: Path) -> None:
    theirs = meerk40t_gcode(DATA / name, tmp_path / "meerk40t.gcode", tmp_path / "home")
    drawing = read_drawing((DATA / name).read_bytes(), name)
    for layer in drawing.layers:  # as MeerK40t's engrave: every shape along its line
        layer.settings = layer_settings({"mode": "line", "speed_mm_min": 2100,
                                         "power_pct": 100}, layer.settings)
    ours = make_job(drawing)
    their_runs, our_runs = cuts(theirs), cuts(ours)
    assert _length(our_runs) == pytest.approx(_length(their_runs), rel=0.01)
    assert _closed(our_runs) == _closed(their_runs) > 0
    core = make_config().core
    our_s = estimate(ours.splitlines(), core).duration_s
    their_s = estimate(theirs.replace("G", "\nG").splitlines(), core).duration_s
    print(f"{name}: cut {_length(our_runs):.1f} mm (MeerK40t {_length(their_runs):.1f}); "
          f"on motiond's planner {our_s:.1f} s (MeerK40t's job {their_s:.1f} s)")
    assert our_s <= their_s * 1.05, "our travel is no worse than the reference's"
