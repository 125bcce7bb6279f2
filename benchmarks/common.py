"""Shared helpers for the benchmarks: corpus location and side-by-side timing."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CORPUS = Path(os.environ.get("MOTIOND_CORPUS", REPO.parent / "shared" / "corpus"))


def corpus_files() -> list[Path]:
    """Every G-code file of the corpus, by name."""
    return sorted(p for p in CORPUS.iterdir() if p.suffix in (".nc", ".gcode"))


def cpu_seconds(work: Callable[[], object]) -> float:
    """CPU time of this process spent in ``work()``: other processes on a shared machine
    slow the wall clock, not this figure."""
    started = time.process_time()
    work()
    return time.process_time() - started


def side_by_side(rounds: int, *works: Callable[[], object]) -> list[float]:
    """Run the works interleaved ``rounds`` times; the best CPU seconds of each."""
    best = [float("inf")] * len(works)
    for _ in range(rounds):
        for index, work in enumerate(works):
            best[index] = min(best[index], cpu_seconds(work))
    return best
