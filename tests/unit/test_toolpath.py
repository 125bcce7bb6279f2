"""The planned toolpath the web UI draws: the real planner, decimated to a bounded size."""

from __future__ import annotations

import itertools
import random

import pytest

from server.offline.toolpath import CUT, GAP, RAPID, Decimator, Segment, plan_toolpath
from tests.conftest import CORPUS, make_config


def test_decimation_merges_collinear_pieces_and_keeps_corners() -> None:
    decimator = Decimator(cap=1000)
    points = [(x * 0.5, 0.0) for x in range(21)] + [(10.0, y * 0.5) for y in range(1, 21)]
    for (x0, y0), (x1, y1) in itertools.pairwise(points):
        decimator.add(Segment(x0, y0, x1, y1, CUT, 600.0, 50.0))
    kept = decimator.finish()
    assert [(s.x0, s.y0, s.x1, s.y1) for s in kept] == [(0, 0, 10, 0), (10, 0, 10, 10)]


def test_decimation_stays_under_the_cap_for_a_long_zigzag() -> None:
    decimator = Decimator(cap=500)
    for i in range(20_000):
        y = (i % 2) * 0.001
        decimator.add(
            Segment(i * 0.01, (1 - i % 2) * 0.001, (i + 1) * 0.01, y, CUT, 600.0, float(i % 100))
        )
    kept = decimator.finish()
    assert len(kept) <= 500
    assert kept[0].x0 == 0.0 and kept[-1].x1 == pytest.approx(200.0)


def test_a_raster_job_is_decimated_under_the_cap_and_ends_where_the_file_ends() -> None:
    lines = (CORPUS / "laser-raster-tree.nc").read_text().splitlines()[:6000]
    core = make_config().core
    path = plan_toolpath(lines, core, 1500)
    assert path["error"] is None and 0 < path["segments"] <= 1500
    assert len(path["points"]) == 2 * (path["segments"] + 1)
    assert set(path["kinds"]) <= {RAPID, CUT} and max(path["powers"]) > 0
    last_x = next(line for line in reversed(lines) if line.startswith("X")).split()[0]
    assert path["end"][0] == pytest.approx(float(last_x[1:]), abs=1e-3)
    assert path["bounds"]["max"][0] == pytest.approx(100.0, abs=0.01)


def decimate(points: list[tuple[float, float]], cap: int, kinds: list[int] | None = None) -> list:
    decimator = Decimator(cap=cap)
    for index, ((x0, y0), (x1, y1)) in enumerate(itertools.pairwise(points)):
        kind = kinds[index % len(kinds)] if kinds else CUT
        decimator.add(Segment(x0, y0, x1, y1, kind, 600.0 + index % 7 * 900, float(index % 100)))
    return decimator.finish()


def test_a_back_and_forth_raster_folds_under_the_cap_and_keeps_its_extent() -> None:
    points = [(0.0, 0.0)]
    for row in range(50_000):  # 100 mm lines, 0.01 mm apart, power changing along the way
        x = 100.0 * ((row + 1) % 2)
        points += [(x, row * 0.01), (x, (row + 1) * 0.01)]
    kept = decimate(points, 1000)
    assert 100 < len(kept) <= 1000
    xs = [x for s in kept for x in (s.x0, s.x1)]
    ys = [y for s in kept for y in (s.y0, s.y1)]
    assert min(xs) == pytest.approx(0.0, abs=1) and max(xs) == pytest.approx(100.0, abs=1)
    assert (kept[0].x0, kept[0].y0) == (0.0, 0.0) and max(ys) == pytest.approx(500.0)
    assert all(a.x1 == b.x0 and a.y1 == b.y0 for a, b in itertools.pairwise(kept)), "connected"


@pytest.mark.parametrize("shape", ["random walk", "huge jumps", "gaps"])
def test_no_path_shape_outgrows_the_cap(shape: str) -> None:
    rng = random.Random(5)
    scale = 1e9 if shape == "huge jumps" else 1.0
    points = [(rng.uniform(-scale, scale), rng.uniform(-scale, scale)) for _ in range(20_000)]
    kinds = [CUT, GAP] if shape == "gaps" else None
    for cap in (100, 1000):
        assert 0 < len(decimate(points, cap, kinds)) <= cap


LASER_OFF_MOVES = ["G21 G90 M4 S500", "G1 X10 F600", "M5", "G1 X20", "M4 S0", "G1 X30",
                   "M4 S800", "G1 X40"]


def test_feed_moves_with_the_laser_off_are_travel_in_the_preview_and_render() -> None:
    from server.offline.estimate import iterate_blocks
    from server.offline.render import collect
    from server.offline.stats import JobStats

    core = make_config(machine={"laser_mode": True}).core
    path = plan_toolpath(LASER_OFF_MOVES, core, 1000)
    assert path["kinds"] == [CUT, RAPID, CUT]  # 0-10 cut, 10-30 laser off (M5, then S0)
    assert path["powers"][0] == 50.0 and path["powers"][2] == 80.0
    drawn = collect(iterate_blocks(LASER_OFF_MOVES, core, JobStats()), laser_mode=True)
    assert [segment[1][0] for segment in drawn.feed] == [10.0, 40.0]
    assert [segment[1][0] for segment in drawn.rapid] == [20.0, 30.0]
    plotter = make_config(machine={"laser_mode": False}).core  # no laser: a feed is a feed
    assert set(plan_toolpath(LASER_OFF_MOVES, plotter, 1000)["kinds"]) == {CUT}
