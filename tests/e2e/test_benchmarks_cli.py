"""The benchmarks' one entry point: ``python -m benchmarks NAME [--quick] [--json]``.

Run as docs/performance.md shows, in a subprocess; only the planner's quick run (about a second) is
measured here, never the full benchmarks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from tests.conftest import REPO

NAMES = ("parser", "planner", "offline", "streaming", "grbl", "klipper", "klipper-host", "lines",
         "plan", "fleet",
         "idle", "import")


def benchmarks(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "benchmarks", *args], cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True,
                          text=True, timeout=120, check=False)


def test_list_names_every_benchmark_with_a_description() -> None:
    listed = benchmarks("--list")
    assert listed.returncode == 0, listed.stderr
    rows = dict(line.split(maxsplit=1) for line in listed.stdout.splitlines())
    assert tuple(rows) == NAMES
    assert all(len(description) > 20 for description in rows.values())


def test_an_unknown_name_is_refused_with_the_known_ones() -> None:
    refused = benchmarks("planer")
    assert refused.returncode == 2
    assert "invalid choice: 'planer'" in refused.stderr
    assert all(name in refused.stderr for name in NAMES)


def test_planner_quick_json_is_one_document_with_the_machine_and_figures_with_units() -> None:
    run = benchmarks("planner", "--quick", "--json")
    assert run.returncode == 0, run.stderr
    document = json.loads(run.stdout)  # the whole of stdout: nothing but the document
    (result,) = document["results"]
    assert (result["name"], result["quick"]) == ("planner", True)
    machine = result["machine"]
    assert machine["node"] and machine["python"] and machine["date"].startswith("20")
    assert "cpu_model" in machine
    figures = [figure for row in result["rows"] for figure in row["figures"].values()]
    assert figures and all(figure["unit"] for figure in figures)
    assert all(isinstance(figure["value"], int | float) for figure in figures)
    ratio = next(row for row in result["rows"] if row["label"] == "ratio")
    assert ratio["figures"]["ratio"]["unit"] == "x" and ratio["figures"]["ratio"]["value"] > 0
    assert "re-plan of 4,096 queued blocks" in run.stderr  # the table went to stderr
