"""Shared helpers for the benchmarks: corpus location, side-by-side timing, and the results.

Every benchmark module exposes ``run(quick: bool) -> BenchResult``: it prints its tables as it
goes and returns the same figures as data (:class:`BenchResult`), which :func:`execute` prints
as one JSON document when asked, so runs can be compared across machines.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
CORPUS = REPO / "tests" / "data" / "corpus"  # real G-code files, sources in SOURCES.md
CPU_MODEL_KEYS = ("model name", "hardware", "cpu model", "processor")  # x86, then ARM / MIPS
JSON_FORMAT = "motiond-benchmarks/1"


def corpus_files() -> list[Path]:
    """Every G-code file of the corpus, by name."""
    return sorted(p for p in CORPUS.iterdir() if p.suffix in (".nc", ".gcode"))


def scratch_data_dir() -> str:
    """A data folder of the benchmark's own, removed at exit: a benchmark's server never reads
    or writes the user's settings and jobs."""
    path = tempfile.mkdtemp(prefix="motiond-bench-")
    atexit.register(shutil.rmtree, path, True)
    return path


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


# -- results ---------------------------------------------------------------------------------------
def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str | None:
    """The CPU's model name from ``/proc/cpuinfo``; None when unreadable or not listed."""
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return None
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and value.strip() and not value.strip().isdigit():
            fields.setdefault(key.strip().lower(), value.strip())
    return next((fields[key] for key in CPU_MODEL_KEYS if key in fields), None)


@dataclass(frozen=True, slots=True)
class Machine:
    """Where and when a benchmark ran (``date``: UTC, ISO 8601, when the run started)."""

    node: str
    cpu_model: str | None
    cpus: int | None
    python: str
    platform: str
    date: str

    @classmethod
    def here(cls) -> Machine:
        return cls(node=platform.node(), cpu_model=cpu_model(), cpus=os.cpu_count(),
                   python=f"{platform.python_implementation()} {platform.python_version()}",
                   platform=platform.platform(),
                   date=datetime.now(UTC).isoformat(timespec="seconds"))


@dataclass(frozen=True, slots=True)
class Figure:
    """One measured number and its unit (``x`` for a ratio, ``lines/s``, ``µs/block``...)."""

    value: float
    unit: str


@dataclass(frozen=True, slots=True)
class Row:
    """One line of a benchmark's table: which table, its subject, its named figures."""

    table: str
    label: str
    figures: dict[str, Figure]
    note: str = ""


@dataclass(slots=True)
class BenchResult:
    """A benchmark's figures as data: its name, the machine, whether quick, and the rows."""

    name: str
    quick: bool
    machine: Machine = field(default_factory=Machine.here)
    rows: list[Row] = field(default_factory=list)

    def add(self, table: str, label: str, note: str = "", **figures: tuple[float, str]) -> None:
        """Record a row; each figure is given as ``name=(value, unit)``."""
        named = {name: Figure(value, unit) for name, (value, unit) in figures.items()}
        self.rows.append(Row(table, label, named, note))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON data; a figure that is not finite (a zero time) becomes null."""
        rows = [{"table": row.table, "label": row.label, "note": row.note,
                 "figures": {name: {"value": finite(figure.value), "unit": figure.unit}
                             for name, figure in row.figures.items()}}
                for row in self.rows]
        return {"name": self.name, "quick": self.quick, "machine": asdict(self.machine),
                "rows": rows}


def finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


# -- running and printing --------------------------------------------------------------------------
def execute(runs: Sequence[Callable[[], BenchResult]], as_json: bool) -> int:
    """Run the benchmarks in turn. Their tables go to stdout; with ``as_json`` the tables go to
    stderr instead (as progress) and stdout gets one JSON document, nothing else."""
    if not as_json:
        for run in runs:
            run()
        return 0
    with contextlib.redirect_stdout(sys.stderr):
        results = [run() for run in runs]
    document = {"format": JSON_FORMAT, "results": [result.to_dict() for result in results]}
    print(json.dumps(document, indent=2, ensure_ascii=False, allow_nan=False))
    return 0


def standalone(run: Callable[[bool], BenchResult], description: str,
               argv: Sequence[str] | None = None) -> int:
    """The command line of one benchmark module run directly (``python -m
    benchmarks.bench_parser [--quick] [--json]``): the same as ``python -m benchmarks NAME``."""
    parser = argparse.ArgumentParser(description=description)
    add_run_options(parser)
    options = parser.parse_args(argv)
    return execute([partial(run, options.quick)], options.json)


def add_run_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true",
                        help="a shorter run: fewer rounds or less work, the same tables")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON document on stdout (the tables go to stderr)")
