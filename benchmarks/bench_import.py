"""Drawing import: a large SVG and a 1,000 x 1,000 px photo made into laser jobs.

The SVG (about 100,000 path segments, half cubic Béziers, in three colours) and the photo
(at 0.1 mm per pixel, so 100 x 100 mm) are made here, seeded, so every run sees the same
files. Each is timed whole (read, layers, toolpaths, G-code text: :mod:`server.cam`); the
SVG beside svgelements' parse of the same bytes alone (the step MeerK40t and vpype start
with) and beside MeerK40t making its Grbl job of the same file (its own environment, no GUI;
its start-up, timed on an empty drawing, taken off). The issue's target: each under 10 s.
"""

from __future__ import annotations

import io
import random
import sys
import time

import numpy as np

from benchmarks.common import BenchResult, standalone

TARGET_S = 10.0


def large_svg(paths: int = 2000, segments: int = 50, seed: int = 1) -> bytes:
    """``paths`` closed paths of ``segments`` pieces each, lines and cubic Béziers."""
    rng = random.Random(seed)
    rows = ['<svg xmlns="http://www.w3.org/2000/svg" width="300mm" height="200mm" '
            'viewBox="0 0 3000 2000">']
    for index in range(paths):
        parts = [f"M{rng.uniform(50, 2950):.3f} {rng.uniform(50, 1950):.3f}"]
        for k in range(segments):
            count = 6 if k % 2 else 2
            numbers = " ".join(f"{rng.uniform(-6, 6):.3f}" for _ in range(count))
            parts.append(("c" if k % 2 else "l") + numbers)
        colour = ("#ff0000", "#0000ff", "#000000")[index % 3]
        rows.append(f'<path stroke="{colour}" fill="none" d="{" ".join(parts)} z"/>')
    rows.append("</svg>")
    return "\n".join(rows).encode()


def photo(size: int = 1000, seed: int = 1) -> bytes:
    """A gray PNG at 254 DPI (0.1 mm per pixel): waves and noise, every gray level."""
    from PIL import Image

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    gray = 127 + 100 * np.sin(xx / 40.0) * np.cos(yy / 55.0) + rng.normal(0, 10, (size, size))
    buffer = io.BytesIO()
    Image.fromarray(gray.clip(0, 255).astype(np.uint8)).save(buffer, "PNG", dpi=(254, 254))
    return buffer.getvalue()


def meerk40t_seconds(svg: bytes) -> float:
    """MeerK40t's wall time to make its job of ``svg``, less its time for an empty one."""
    import tempfile
    from pathlib import Path

    from tests.support.meerk40t import meerk40t_gcode

    empty = b'<svg xmlns="http://www.w3.org/2000/svg" width="10mm" height="10mm"/>'
    with tempfile.TemporaryDirectory(prefix="motiond-bench-") as folder:
        times = []
        for name, data in (("empty.svg", empty), ("large.svg", svg)):
            path = Path(folder) / name
            path.write_bytes(data)
            started = time.perf_counter()
            meerk40t_gcode(path, path.with_suffix(".gcode"), Path(folder) / "home")
            times.append(time.perf_counter() - started)
    return times[1] - times[0]


def timed(work: object) -> tuple[float, float, object]:
    """Wall and CPU seconds of ``work()``, and its result."""
    assert callable(work)
    wall, cpu = time.perf_counter(), time.process_time()
    value = work()
    return time.perf_counter() - wall, time.process_time() - cpu, value


def run(quick: bool) -> BenchResult:
    import svgelements

    from server.cam.job import make_job, read_drawing
    from server.cam.model import layer_settings

    result = BenchResult("import", quick)
    svg = large_svg(paths=400 if quick else 2000)
    segments = (400 if quick else 2000) * 50
    parse_wall, _, _ = timed(lambda: list(svgelements.SVG.parse(io.BytesIO(svg)).elements()))
    wall, cpu, gcode = timed(lambda: make_job(read_drawing(svg, "large.svg")))
    print(f"{'drawing':44} {'wall s':>7} {'cpu s':>6} {'lines':>9}  note")
    note = f"svgelements parse alone {parse_wall:.2f} s; target < {TARGET_S:g} s"
    label = f"SVG {len(svg) / 1e6:.1f} MB, {segments:,} segments"
    print(f"{label:44} {wall:7.2f} {cpu:6.2f} "
          f"{str(gcode).count(chr(10)):9,}  {note}")
    result.add("import", "large SVG", note, wall_s=(wall, "s"), cpu_s=(cpu, "s"),
               parse_s=(parse_wall, "s"), bytes=(len(svg), "B"))
    theirs = meerk40t_seconds(svg)
    print(f"{'the same SVG, MeerK40t':44} {theirs:7.2f} {'':6} {'':9}  ours "
          f"{theirs / wall:.1f}x faster")
    result.add("import", "large SVG, MeerK40t", "start-up taken off",
               wall_s=(theirs, "s"), ratio=(theirs / wall, "x"))
    image = photo(size=300 if quick else 1000)
    for dither in ("grayscale", "floyd-steinberg", "stucki"):
        def engrave(dither: str = dither) -> str:
            drawing = read_drawing(image, "photo.png")
            layer = drawing.layers[0]
            layer.settings = layer_settings({"dither": dither}, layer.settings)
            return make_job(drawing)

        wall, cpu, gcode = timed(engrave)
        label = f"{'300' if quick else '1,000'} px image at 0.1 mm, {dither}"
        print(f"{label:44} {wall:7.2f} {cpu:6.2f} {str(gcode).count(chr(10)):9,}")
        result.add("import", label, "", wall_s=(wall, "s"), cpu_s=(cpu, "s"))
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
