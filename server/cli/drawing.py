"""``motiond import FILE -o job.gcode``: a drawing (SVG, DXF, PNG, JPEG) made into a laser
job with :mod:`server.cam`, each layer's settings from ``--layer``; the layers are listed on
stderr (``--json``: the drawing and the job as JSON on stdout). ``--material NAME`` applies a
material of the machine's library (saved from the web UI) before ``--layer``. Exit status: 0,
1 for a file refused, 2 for a missing extra or bad options."""

from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

from server.config import Config
from server.errors import DrawingError

CAM_PACKAGES = ("svgelements", "ezdxf", "PIL", "shapely")


def missing_cam_packages() -> list[str]:
    """The ``[cam]`` extra's packages not installed."""
    return [name for name in CAM_PACKAGES if not _installed(name)]


def _installed(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ValueError:  # in sys.modules as None: blocked
        return False


def import_command(args: Any, config: Config) -> int:
    """``motiond import FILE -o OUT``."""
    missing = missing_cam_packages()
    if missing:
        print(f"motiond import needs {', '.join(missing)}: pip install 'motiond[cam]'",
              file=sys.stderr)
        return 2
    from server.cam.job import make_job, read_drawing
    from server.cam.materials import apply_material
    from server.cam.model import apply_layer_options, parse_layer_option

    path: Path = args.file
    try:
        data = path.read_bytes()
    except OSError as exc:
        print(f"motiond: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 1
    started = time.perf_counter()
    bar = _bar(path.name, enabled=not args.json and sys.stderr.isatty())
    try:
        drawing = read_drawing(data, path.name, width_mm=args.width_mm, dpi=args.dpi)
        if args.material:
            apply_material(drawing, _library(config), args.material)
        apply_layer_options(drawing, dict(parse_layer_option(text) for text in args.layer))
        drawing.reorder([name for name in (args.order or "").split(",") if name.strip()])
        gcode = make_job(drawing, config.laser_max_s(),
                         lambda fraction: bar.update(round(100 * fraction) - bar.n))
    except DrawingError as exc:
        print(f"motiond: {exc}", file=sys.stderr)
        return 1
    finally:
        bar.close()
    args.output.write_text(gcode)
    elapsed_s = time.perf_counter() - started
    lines = gcode.count("\n")
    if args.json:
        print(json.dumps({"drawing": drawing.describe(), "output": str(args.output),
                          "lines": lines, "elapsed_s": round(elapsed_s, 3)}, indent=2))
        return 0
    for warning in drawing.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    for layer in drawing.layers:
        print(_describe_layer(layer.describe()), file=sys.stderr)
    print(f"wrote {args.output} ({lines:,} lines in {elapsed_s:.2f} s)", file=sys.stderr)
    return 0


def _library(config: Config) -> Any:
    """The machine's material library (``materials.json`` in its data folder; none: empty)."""
    from server.cam.materials import parse_library
    from server.paths import materials_path

    path = materials_path(config.core)
    try:
        return parse_library(path.read_text(), str(path))
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise DrawingError(f"cannot read {path}: {exc.strerror}") from exc


def _bar(label: str, enabled: bool) -> Any:
    """A progress bar in percent of the layers' passes made (tqdm, on a terminal)."""
    from tqdm import tqdm

    return tqdm(total=100, unit="%", desc=label, disable=not enabled, leave=False)


def _describe_layer(layer: dict[str, Any]) -> str:
    s = layer["settings"]
    what = (f"{layer['image'][0]} x {layer['image'][1]} px" if layer["image"]
            else f"{layer['shapes']} shapes ({layer['closed']} closed)")
    state = "" if s["enabled"] else " (off)"
    return (f"  {layer['name']:<8} {s['mode']:<5} {what}, {s['speed_mm_min']:g} mm/min, "
            f"{s['power_pct']:g} %, {s['passes']} pass(es){state}")
