"""Run motiond's benchmarks by name.

    python -m benchmarks NAME [--quick] [--json]     # NAME: parser, planner, offline, streaming,
                                                     #       grbl, klipper, klipper-host, lines,
                                                     #       idle, plan, fleet, import
    python -m benchmarks klipper [--runs N] [--motiond-tree DIR] [--hosts klippy motiond]
    python -m benchmarks all [--quick] [--json]
    python -m benchmarks --list

The tables print as each benchmark runs; ``--json`` prints one JSON document on stdout instead
(the tables go to stderr), with the machine, the date and every figure with its unit.
A benchmark's module is imported only when it runs (``--list`` imports none of them).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence

from benchmarks.common import BenchResult, add_run_options, execute
from benchmarks.klipper_options import add_options, options_of

BENCHMARKS: dict[str, tuple[str, str]] = {  # name: (module, one-line description)
    "parser": ("benchmarks.bench_parser",
               "parser lines/s on the whole corpus, against PyPI pygcode"),
    "planner": ("benchmarks.bench_planner",
                "re-plan of 4,096 blocks against plain-Python loops; append + pop blocks/s"),
    "offline": ("benchmarks.bench_offline",
                "estimate blocks/s and full 1 kHz execution real-time factor per corpus file"),
    "streaming": ("benchmarks.bench_streaming",
                  "TCP streaming lines/s against a bare asyncio server; real-time raster rate"),
    "grbl": ("benchmarks.bench_grbl_link",
             "lines/s through motiond to a Grbl controller against streaming to it directly"),
    "klipper": ("benchmarks.bench_klipper",
                "Klipper backend against klippy on the stock firmware (rig): CPU, bytes, timing"),
    "klipper-host": ("benchmarks.bench_klipper_host",
                     "Klipper backend's host half on a virtual clock: CPU at 20,000 segments/s"),
    "lines": ("benchmarks.bench_lines",
              "host CPU per G-code line: the Klipper raster over TCP into motiond on the sim"),
    "plan": ("benchmarks.bench_plan",
             "play of a 2-million-line raster: ready, timed, the operator's ? meanwhile"),
    "fleet": ("benchmarks.bench_fleet",
              "N motiond (default 50) on one mosquitto: idle CPU/RSS, staleness, fleet, job"),
    "idle": ("benchmarks.bench_idle",
             "CPU of an idle server: motiond on the sim, the Klipper backend's event loop"),
    "import": ("benchmarks.bench_import",
               "drawing to job: a 100,000-segment SVG and a 1,000 px photo, beside svgelements"),
}


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks", description="Run motiond's benchmarks by name.")
    parser.add_argument("name", nargs="?", choices=[*BENCHMARKS, "all"],
                        help="the benchmark to run, or all of them in turn")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    add_run_options(parser)
    parser.add_argument("--machines", type=int, help="fleet: how many motiond (default 50)")
    add_options(parser)
    options = parser.parse_args(argv)
    if options.name is None and not options.list:
        parser.error("name a benchmark (or all), or --list them")
    return options


def runner(name: str, options: argparse.Namespace, header: bool) -> Callable[[], BenchResult]:
    """Import the benchmark's module and run it (with a title line when running several)."""

    def run() -> BenchResult:
        module, description = BENCHMARKS[name]
        if header:
            print(f"\n== {name}: {description}\n")
        extra = options_of(options) if name == "klipper" else {}
        if name == "plan":
            extra = {"motiond_tree": options.motiond_tree}
        if name == "fleet":
            extra = {"machines": options.machines}
        if name == "lines":
            extra = {"runs": options.runs, "motiond_tree": options.motiond_tree}
        result: BenchResult = importlib.import_module(module).run(options.quick, **extra)
        return result

    return run


def main(argv: Sequence[str] | None = None) -> int:
    options = parse_args(argv)
    if options.list:
        for name, (_, description) in BENCHMARKS.items():
            print(f"{name:12} {description}")
        return 0
    names = list(BENCHMARKS) if options.name == "all" else [options.name]
    runs = [runner(name, options, header=len(names) > 1) for name in names]
    return execute(runs, options.json)


if __name__ == "__main__":
    sys.exit(main())
