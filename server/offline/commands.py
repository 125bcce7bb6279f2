"""The ``motiond estimate`` and ``motiond render`` commands: reading the job, a progress bar,
the garbage collector paused, and the figures printed as text or JSON.

The work itself is the offline pipeline (:mod:`server.offline.estimate`) and the drawing
(:mod:`server.offline.render`).
"""

from __future__ import annotations

import contextlib
import gc
import importlib.util
import json
import sys
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

from server.config import Config
from server.offline.estimate import estimate, iterate_blocks, machine_interpreter
from server.offline.stats import JobStats, format_duration


@contextlib.contextmanager
def collection_paused() -> Iterator[None]:
    """No automatic garbage collection during a one-shot command (``motiond estimate``).

    The pipeline makes no reference cycles (blocks are freed by reference counting as they
    are popped), so a collection finds nothing; but each full one re-scans everything loaded,
    the list of the job's lines among it: 15 % of a 300,000-line raster's estimate.
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _read_lines(path: Path) -> list[str]:
    return path.read_text(errors="replace").splitlines()


def _progress(total: int, label: str, enabled: bool) -> tuple[Callable[[int], None], Any]:
    from tqdm import tqdm

    bar = tqdm(
        total=total, unit="line", desc=label, disable=not enabled, leave=False, mininterval=0.2
    )
    last = [0]

    def update(number: int) -> None:
        if number - last[0] >= 2000 or number == total:
            bar.update(number - last[0])
            last[0] = number

    return update, bar


def estimate_command(args: Any, config: Config) -> int:
    """``motiond estimate FILE``."""
    path: Path = args.file
    try:
        lines = _read_lines(path)
    except OSError as exc:
        print(f"motiond: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 1
    show = not args.no_progress and not args.json and sys.stderr.isatty() and len(lines) > 5000
    update, bar = _progress(len(lines), path.name, show)
    with collection_paused():
        stats = estimate(lines, config.core, update if show else None, machine_interpreter(config))
    bar.close()
    if args.json:
        print(json.dumps({"file": str(path), **_public(asdict(stats))}, indent=2))
    else:
        print(describe(path, stats, config.core.axis_names))
    return 1 if stats.error else 0


def _public(fields: dict[str, Any]) -> dict[str, Any]:
    return {key: value for key, value in fields.items() if not key.startswith("_")}


def _count(number: int, noun: str) -> str:
    return f"{number:,} {noun}{'' if number == 1 else 's'}"


def describe(path: Path, stats: JobStats, axis_names: tuple[str, ...]) -> str:
    rows = [
        f"{path}",
        f"  time        {format_duration(stats.duration_s)}",
        f"  cutting     {stats.cut_mm:,.1f} mm",
        f"  rapids      {stats.rapid_mm:,.1f} mm",
        f"  moves       {stats.moves:,} ({_count(stats.blocks, 'planned block')}, "
        f"{_count(stats.lines, 'line')})",
        f"  max speed   {stats.max_speed_mm_s * 60:,.0f} mm/min",
    ]
    if stats.bbox_min_mm:
        extent = "  ".join(
            f"{name} {low:.3f}..{high:.3f}"
            for name, low, high in zip(
                axis_names, stats.bbox_min_mm, stats.bbox_max_mm, strict=True
            )
        )
        rows.append(f"  extent      {extent}")
    if stats.error:
        rows.append(f"  STOPPED at line {stats.error_line}: {stats.error}")
    return "\n".join(rows)


def render_command(args: Any, config: Config) -> int:
    """``motiond render FILE -o OUT``."""
    from server.offline.render import collect, draw

    path: Path = args.file
    output: Path = args.output
    if output.suffix.lower() not in (".svg", ".png"):
        print("motiond: the output must end in .svg or .png", file=sys.stderr)
        return 2
    if importlib.util.find_spec("matplotlib") is None:
        print("motiond render needs matplotlib: pip install 'motiond[render]'", file=sys.stderr)
        return 2
    try:
        lines = _read_lines(path)
    except OSError as exc:
        print(f"motiond: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 1
    stats = JobStats()
    blocks = iterate_blocks(lines, config.core, stats, interpreter=machine_interpreter(config))
    toolpath = collect(blocks, config.core.machine.laser_mode)
    title = f"{path.name} — {format_duration(stats.duration_s)}, {stats.cut_mm:,.0f} mm cut"
    if stats.error:
        title += f" (stopped at line {stats.error_line})"
    draw(toolpath, output, title)
    print(
        f"wrote {output} ({len(toolpath.feed):,} feed and {len(toolpath.rapid):,} rapid segments)"
    )
    if stats.error:
        print(f"  stopped at line {stats.error_line}: {stats.error}", file=sys.stderr)
    return 1 if stats.error else 0
