"""The ``motiond estimate`` and ``motiond render`` commands (and the interpreter of the
configured machine that ``check-config`` builds): reading the job, a progress bar,
the garbage collector paused, and the figures printed as text or JSON.

The work itself is the offline pipeline (:mod:`server.offline.estimate`) and the drawing
(:mod:`server.offline.render`). A job's time never depends on where it is placed: it is run
with soft limits off, and whether it fits the travel from ``--origin`` (the work origin in
machine mm, where the tool starts; default machine zero) is reported apart
(:mod:`server.offline.fit`). Exit status: 0, 1 for a line the machine refuses, 3 for a job
that does not fit with ``--require-fit``.
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
from server.gcode.interpreter import Interpreter
from server.gcode.parser import parse_line
from server.kernel.kernel import Kernel
from server.offline.estimate import estimate, iterate_blocks
from server.offline.fit import Fit, check_fit
from server.offline.stats import JobStats, format_duration
from server.runtime.clock import VirtualClock

MISFIT_EXIT = 3


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
    origin = tuple(args.origin or ())
    interpreter = machine_interpreter(config, origin)
    with collection_paused():
        stats = estimate(lines, config.core, update if show else None, interpreter)
    bar.close()
    fit = job_fit(stats, config, interpreter.wco())
    names = config.core.axis_names
    if args.json:
        fields = _public(asdict(stats))
        for option in ("keep_timeline", "count_start"):  # how it was summed, not what
            fields.pop(option, None)
        print(json.dumps({"file": str(path), **fields, "fit": fit.as_dict(names)}, indent=2))
    else:
        print(describe(path, stats, names))
        print(describe_fit(fit, names, interpreter.wco()))
    return exit_status(stats, fit, args)


def job_fit(stats: JobStats, config: Config, wco_mm: tuple[float, ...]) -> Fit:
    """The job's extent (machine mm) against the configured travel."""
    axes = list(config.core.axes.values())
    return check_fit(stats.bbox_min_mm, stats.bbox_max_mm, [a.min_mm for a in axes],
                     [a.max_mm for a in axes], config.core.axis_names, wco_mm)


def exit_status(stats: JobStats, fit: Fit, args: Any) -> int:
    if stats.error:
        return 1
    strict = args.require_fit and not args.no_limits
    return MISFIT_EXIT if strict and not fit.fits else 0


def describe_fit(fit: Fit, names: tuple[str, ...], origin_mm: tuple[float, ...]) -> str:
    """``size``, the origin the fit was checked from, and whether the job fits."""
    where = " ".join(f"{name}{value:g}" for name, value in zip(names, origin_mm, strict=True))
    rows = []
    if fit.extent_min_mm:
        size = " x ".join(
            f"{name} {high - low:.3f}" for name, low, high
            in zip(names, fit.extent_min_mm, fit.extent_max_mm, strict=True))
        rows.append(f"  size        {size} mm")
    verdict = "yes" if fit.fits else "NO: " + "; ".join(m.describe() for m in fit.misfits)
    rows.append(f"  fits        {verdict} (work origin at machine {where})")
    return "\n".join(rows)


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
    interpreter = machine_interpreter(config, tuple(args.origin or ()))
    blocks = iterate_blocks(lines, config.core, stats, interpreter=interpreter)
    toolpath = collect(blocks, config.core.machine.laser_mode)
    title = f"{path.name} — {format_duration(stats.duration_s)}, {stats.cut_mm:,.0f} mm cut"
    if stats.error:
        title += f" (stopped at line {stats.error_line})"
    draw(toolpath, output, title, by_power=args.power)
    print(
        f"wrote {output} ({len(toolpath.feed):,} feed and {len(toolpath.rapid):,} rapid segments)"
    )
    fit = job_fit(stats, config, interpreter.wco())
    print(describe_fit(fit, config.core.axis_names, interpreter.wco()))
    if stats.error:
        print(f"  stopped at line {stats.error_line}: {stats.error}", file=sys.stderr)
    return exit_status(stats, fit, args)


def machine_interpreter(config: Config, origin_mm: tuple[float, ...] = ()) -> Interpreter:
    """The interpreter the configured machine would read a job with: its settings and the
    M-codes its modules claim (the modules are built, never started), soft limits off (a
    job's time does not depend on where it is placed: :mod:`server.offline.fit` checks
    that). ``origin_mm`` (machine mm, missing axes 0) is the G54 work origin, set as
    ``G10 L2 P1`` would, and where the tool starts.

    Raises:
        ConfigError: the config is invalid, or two modules claim one code.
    """
    interpreter = Kernel(config, VirtualClock()).machine.new_interpreter(soft_limits=False)
    if any(origin_mm):
        names = config.core.axis_names
        origin = tuple(origin_mm[i] if i < len(origin_mm) else 0.0 for i in range(len(names)))
        words = " ".join(f"{name}{value:.6f}" for name, value in zip(names, origin, strict=True))
        interpreter.execute(parse_line(f"G10 L2 P1 {words}"))
        interpreter.set_position(origin)
    return interpreter
