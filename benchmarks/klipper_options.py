"""The command-line options of ``python -m benchmarks klipper`` (importing nothing heavy, so
``python -m benchmarks --list`` stays quick)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

HOSTS = ("klippy", "motiond")
JOBS = ("raster", "circles", "long", "idle")  # each job's name's first word


def add_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=int, help="klipper, lines: runs of each job per host "
                        "(default 3, 1 with --quick; lines: 5, 2)")
    parser.add_argument("--motiond-tree", type=Path, help="klipper, lines: motiond's source tree "
                        "to measure (default: this checkout)")
    parser.add_argument("--hosts", nargs="+", choices=HOSTS, default=list(HOSTS),
                        help="klipper: which hosts to measure")
    parser.add_argument("--logs", type=Path, help="klipper: keep the rigs' serial and GPIO "
                        "logs and the hosts' logs in this folder (default: a temporary one)")
    parser.add_argument("--lead-time-s", type=float, help="klipper: motiond's [backend] "
                        "lead_time_s (default: motiond's own, 0.3 s)")
    parser.add_argument("--jobs", nargs="+", choices=JOBS, default=list(JOBS),
                        help="klipper: which jobs to run (long: the long moves)")
    parser.add_argument("--rig-pause-ms", type=float, default=0.0, help="klipper: stop the "
                        "rig's simulator this long every 1.5 s (a loaded host's lag)")
    parser.add_argument("--feed", choices=("stream", "job"), default="stream", help="klipper: "
                        "how motiond gets each job: streamed by a sender over TCP (character "
                        "counting), or stored and started with 'play' (as klippy gets the "
                        "whole job)")
    parser.add_argument("--clock-fit", action="store_true", help="klipper: run motiond at "
                        "debug level and check each of its clock polls against the rig's clock "
                        "(its CPU then includes that logging)")


def options_of(options: Any) -> dict[str, Any]:
    return {"runs": options.runs, "motiond_tree": options.motiond_tree, "hosts": options.hosts,
            "logs": options.logs, "lead_time_s": options.lead_time_s,
            "rig_pause_ms": options.rig_pause_ms, "job_names": options.jobs,
            "feed": options.feed, "clock_fit": options.clock_fit}
