"""A job's plan keeps a bounded timeline whatever the number of blocks (a raster of millions
of short lines): the stride between kept block end times doubles as the job grows, and every
kept time is the exact planned time at its block count."""

from __future__ import annotations

import numpy as np
import pytest

from server.offline import stats
from server.offline.stats import JobStats


def test_the_timeline_keeps_at_most_its_bound_and_each_kept_time_is_exact(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(stats, "TIMELINE_MARKS", 8)
    job = JobStats(keep_timeline=True)
    durations = np.linspace(0.5, 3.0, 1000)
    for piece in np.array_split(durations, 37):  # batches of settled blocks, as the planner
        job._record(piece)
    timeline, stride = job.timeline(), job.timeline_stride
    exact = np.cumsum(durations)
    assert 0 < len(timeline) <= 8
    assert stride > 1
    assert np.allclose(timeline, exact[stride - 1 :: stride][: len(timeline)])


def test_a_short_job_keeps_every_block_end() -> None:
    job = JobStats(keep_timeline=True)
    job._record(np.array([1.0, 2.0]))
    job._record(np.array([0.5]))
    assert job.timeline_stride == 1
    assert job.timeline().tolist() == [1.0, 3.0, 3.5]
