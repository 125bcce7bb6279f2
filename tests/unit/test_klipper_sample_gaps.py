"""How often the Klipper backend asks to be sampled while motion runs: what turns within the
share (half the hold-back) after a sample leaves at it, so no two samples come closer than that
on the rig benchmark's jobs, while their steps stay exact; and each of those sparse ticks is
one call of the step generator, one sample (not sliced as a late tick is). Each runs through
the real planner, step generator and backend on a virtual clock
(``benchmarks.bench_klipper_host``), ticking when the backend asks, as the server does."""

from __future__ import annotations

import pytest

from benchmarks.bench_klipper_host import OfflineBackend, execute
from benchmarks.klipper_rig_hosts import STEPS_PER_MM
from benchmarks.klipper_rig_jobs import Job, circles, long_moves, raster
from server.backends.klipper.schedule import SHARE_OF_HOLD_BACK


@pytest.mark.parametrize("job", [raster(lines=6), circles(turns=3), long_moves(count=4)],
                         ids=lambda job: job.name)
def test_samples_in_motion_come_at_least_the_share_apart_and_the_steps_stay_exact(
        job: Job, monkeypatch: pytest.MonkeyPatch) -> None:
    asked: list[tuple[float, float]] = []  # (sample, the next one it asked for)
    next_sample_s = OfflineBackend.next_sample_s

    def recording(backend: OfflineBackend, time_s: float) -> float:
        due_s = next_sample_s(backend, time_s)
        asked.append((time_s, due_s))
        return due_s

    monkeypatch.setattr(OfflineBackend, "next_sample_s", recording)
    _, motion_s, backend = execute(0.0, job)
    share_s = max(backend.flush_s, SHARE_OF_HOLD_BACK * backend.hold_back_s)
    assert share_s == pytest.approx(0.075)  # the default lead's
    # in motion: from the first sample after the start to the one before the end (the first
    # and the last asked for at once: a start pending, the motion's end)
    gaps_s = [due_s - time_s for time_s, due_s in asked if 0.0 < time_s < motion_s - 0.3]
    assert len(gaps_s) >= 5 and min(gaps_s) >= share_s, sorted(gaps_s)[:5]
    for index, axis in enumerate(backend.axes):
        assert axis.position == round(job.end[index] * STEPS_PER_MM), axis.name


def test_a_sparse_tick_of_the_rig_raster_is_one_sample(monkeypatch: pytest.MonkeyPatch) -> None:
    """~80 blocks a sample (0.1 mm segments at 100 mm/s, 9 samples a second): under the
    backend's ``blocks_per_call``, so no tick is sliced into samples of its own."""
    samples: list[float] = []
    sample = OfflineBackend.sample

    def counting(backend: OfflineBackend, time_s: float, *args: object) -> None:
        samples.append(time_s)
        sample(backend, time_s, *args)

    monkeypatch.setattr(OfflineBackend, "sample", counting)
    job = raster(lines=6)
    _, _, backend = execute(0.0, job)
    ticks = backend.ticks  # type: ignore[attr-defined]
    assert len(job.path) / ticks > 64  # blocks a tick: more than a late tick's slice
    assert len(samples) <= ticks + 1, (len(samples), ticks)  # (the first tick, at rest)
