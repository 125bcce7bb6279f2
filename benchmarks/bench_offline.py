"""Offline pipeline throughput on every corpus file.

* estimate: blocks/s and real-time factor (job seconds per wall second);
* full virtual execution by the step generator at 1 kHz: real-time factor and steps/s;
* baseline, side by side: parsing alone, so the ratio shows what planning costs on top.

Parsing and the estimate run interleaved, three rounds each, and the best CPU time of each
counts (see :func:`benchmarks.common.side_by_side`); the full execution runs once.

Run: ``python -m benchmarks offline [--quick] [--json]`` (quick: skip the full execution of
the big raster file).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from benchmarks.common import BenchResult, corpus_files, side_by_side, standalone
from server.backends.sim import SimBackend
from server.config import CoreConfig, load_config
from server.gcode.parser import parse_line
from server.offline.estimate import JobStats, estimate, execute

QUICK_MAX_BLOCKS = 20_000  # quick: files with more blocks are estimated, not executed


def measure_file(result: BenchResult, path: Path, core: CoreConfig, quick: bool) -> None:
    """Parse and estimate side by side; then, unless skipped, execute at 1 kHz."""
    lines = path.read_text(errors="replace").splitlines()
    results: list[JobStats] = []
    parse_s, estimate_s = side_by_side(
        3,
        lambda: [parse_line(text) for text in lines],
        lambda: results.append(estimate(lines, core)),
    )
    stats = results[-1]
    row = (f"{path.name:30} {stats.blocks:7,} {len(lines) / parse_s:14,.0f} "
           f"{stats.blocks / estimate_s:18,.0f} {stats.duration_s / estimate_s:8,.0f}x")
    figures = {"blocks": (stats.blocks, "blocks"), "parse": (len(lines) / parse_s, "lines/s"),
               "estimate": (stats.blocks / estimate_s, "blocks/s"),
               "estimate_rtf": (stats.duration_s / estimate_s, "x")}
    if quick and stats.blocks > QUICK_MAX_BLOCKS:
        print(row + f" {'(skipped)':>12}")
        result.add("corpus", path.name, note="execution skipped (quick)", **figures)
        return
    backend = SimBackend(core.axis_names, [a.steps_per_mm for a in core.axes.values()],
                         history_samples=0)
    started = time.perf_counter()
    full = execute(lines, core, backend)
    execute_s = time.perf_counter() - started
    stops = "" if not stats.error else f"stops at line {stats.error_line}"
    print(row + f" {full.duration_s / execute_s:11,.0f}x "
          f"{backend.steps_travelled / execute_s:11,.0f}" + (f"  ({stops})" if stops else ""))
    result.add("corpus", path.name, note=stops, **figures,
               execute_rtf=(full.duration_s / execute_s, "x"),
               steps=(backend.steps_travelled / execute_s, "steps/s"))


def run(quick: bool) -> BenchResult:
    result = BenchResult("offline", quick)
    core = load_config().core
    core.machine.soft_limits = False  # the corpus comes from other machines
    print(f"{'file':30} {'blocks':>7} {'parse lines/s':>14} {'estimate blocks/s':>18} "
          f"{'est. RTF':>9} {'execute RTF':>12} {'steps/s':>11}")
    for path in corpus_files():
        measure_file(result, path, core, quick)
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
