"""Offline pipeline throughput on every corpus file.

* estimate: blocks/s and real-time factor (job seconds per wall second);
* full virtual execution by the step generator at 1 kHz: real-time factor and steps/s;
* baseline, side by side: parsing alone, so the ratio shows what planning costs on top;
* a 300,000-line LightBurn-style raster (0.1 mm ``G1 X.. S..`` segments back and forth, one
  ``S`` per segment), written to a temporary file and read back as ``motiond estimate`` reads
  it: the estimate against PyPI pygcode parsing every line, side by side, both with garbage
  collection paused as ``motiond estimate`` runs (target: the estimate at least 4x pygcode).

Parsing and the estimate run interleaved, three rounds each, and the best CPU time of each
counts (see :func:`benchmarks.common.side_by_side`); the full execution runs once.

Run: ``python -m benchmarks offline [--quick] [--json]`` (quick: skip the full execution of
the big raster file, two rounds for the 300,000-line raster).
"""

from __future__ import annotations

import random
import sys
import tempfile
import time
from pathlib import Path

from pygcode import Line as PygcodeLine

from benchmarks.common import BenchResult, corpus_files, side_by_side, standalone
from server.backends.sim import SimBackend
from server.cli.offline import collection_paused
from server.config import CoreConfig
from server.config_loader import load_config
from server.gcode.parser import parse_line
from server.offline.estimate import estimate, execute
from server.offline.stats import JobStats

QUICK_MAX_BLOCKS = 20_000  # quick: files with more blocks are estimated, not executed
RASTER_LINES = 300_000
RASTER_ROW_SEGMENTS = 1000
ESTIMATE_TARGET = 4.0  # the estimate at least this many times pygcode's parse rate


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


def lightburn_raster(count: int) -> list[str]:
    """A raster as LightBurn writes one: rows of 0.1 mm ``G1`` segments, back and forth, each
    with its own power (``S`` 0-1000, a grey image), a ``G1 Y.. S0`` step between rows."""
    rng = random.Random(1)
    lines = ["G21 G90", "M4 S0", "G1 F6000"]
    row = 0
    while len(lines) < count:
        lines.append(f"G1 Y{row * 0.1:.1f} S0")
        columns = range(1, RASTER_ROW_SEGMENTS)
        for column in columns if row % 2 == 0 else reversed(columns[:-1]):
            lines.append(f"G1 X{column * 0.1:.1f} S{rng.randrange(1000)}")
        row += 1
    return lines[:count]


def pygcode_parse(lines: list[str]) -> None:
    for text in lines:
        PygcodeLine(text).block.words  # noqa: B018 - touch the full output


def measure_raster(result: BenchResult, core: CoreConfig, quick: bool) -> None:
    """The 300,000-line raster: ``estimate`` against pygcode parsing it, side by side."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "raster-300k.nc"
        path.write_text("\n".join(lightburn_raster(RASTER_LINES)) + "\n")
        lines = path.read_text().splitlines()  # as motiond estimate reads a file
    stats: list[JobStats] = []
    with collection_paused():  # as motiond estimate runs: the same for both
        parse_s, estimate_s = side_by_side(
            2 if quick else 3,
            lambda: pygcode_parse(lines),
            lambda: stats.append(estimate(lines, core)),
        )
    ratio = parse_s / estimate_s
    verdict = "OK" if ratio >= ESTIMATE_TARGET else "BELOW TARGET"
    print(f"\n{len(lines):,}-line 0.1 mm raster (LightBurn style, S per segment), best of "
          f"{2 if quick else 3}: estimate {len(lines) / estimate_s:,.0f} lines/s "
          f"({stats[-1].blocks:,} blocks, {stats[-1].duration_s:,.1f} s of job), pygcode parse "
          f"{len(lines) / parse_s:,.0f} lines/s: {ratio:.2f}x (target {ESTIMATE_TARGET:g}x) "
          f"{verdict}")
    result.add("raster 300k", "estimate vs pygcode", lines=(len(lines), "lines"),
               estimate=(len(lines) / estimate_s, "lines/s"),
               pygcode=(len(lines) / parse_s, "lines/s"), ratio=(ratio, "x"),
               job=(stats[-1].duration_s, "s"))


def run(quick: bool) -> BenchResult:
    result = BenchResult("offline", quick)
    core = load_config().core
    core.machine.soft_limits = False  # the corpus comes from other machines
    print(f"{'file':30} {'blocks':>7} {'parse lines/s':>14} {'estimate blocks/s':>18} "
          f"{'est. RTF':>9} {'execute RTF':>12} {'steps/s':>11}")
    for path in corpus_files():
        measure_file(result, path, core, quick)
    measure_raster(result, core, quick)
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
