"""What the laser burnt, rasterised, against the drawing rendered by a reference renderer.

A job's G-code runs through the offline pipeline (parser, interpreter, planner: the blocks
the machine executes, :func:`server.offline.estimate.iterate_blocks`); the blocks that fire
(a feed move, M3/M4, S > 0) are the burn. Both the burn and the reference are drawn by
resvg (PyPI ``resvg-py``) at 0.1 mm per pixel, so the comparison sees geometry, not two renderers'
antialiasing: the burn as strokes ``stroke_mm`` wide (a line layer: round caps, as the kerf)
or ``interval_mm`` wide with butt caps (a fill's hatch lines tile the region).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import resvg_py
from PIL import Image

from server.cli.offline import machine_interpreter
from server.config import Config
from server.motion.moves import MoveKind, ToolMode
from server.offline.estimate import iterate_blocks
from server.offline.stats import JobStats

PX_PER_MM = 10.0


@dataclass(slots=True)
class Burn:
    """The burnt pieces (mm, Y up), the S of each, and the planned speeds (mm/s)."""

    segments: np.ndarray  # (n, 4): x0, y0, x1, y1
    s_values: np.ndarray
    entry_mm_s: np.ndarray
    nominal_mm_s: np.ndarray


def burn(gcode: str, config: Config) -> Burn:
    """The job run on ``config``'s machine, soft limits off (an overscan may pass zero)."""
    rows, s, entry, nominal = [], [], [], []
    stats = JobStats()
    interpreter = machine_interpreter(config)
    for block in iterate_blocks(gcode.splitlines(), config.core, stats, interpreter=interpreter):
        move = block.move
        if (move is None or move.kind not in (MoveKind.FEED, MoveKind.ARC)
                or move.tool_mode is ToolMode.OFF or move.s_value <= 0):
            continue
        rows.append((*block.start_mm[:2], *block.end_mm[:2]))
        s.append(move.s_value)
        entry.append(block.entry_mm_s)
        nominal.append(block.nominal_mm_s)
    assert stats.error is None, stats.error
    return Burn(np.array(rows).reshape(-1, 4), np.array(s), np.array(entry), np.array(nominal))


def burn_mask(segments: np.ndarray, width_mm: float, height_mm: float, stroke_mm: float,
              cap: str = "round") -> np.ndarray:
    """The burnt pieces drawn ``stroke_mm`` wide, as a boolean image (row 0 at the top)."""
    path = " ".join(f"M{x0:.4f},{height_mm - y0:.4f}L{x1:.4f},{height_mm - y1:.4f}"
                    for x0, y0, x1, y1 in segments.tolist())
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{width_mm}mm" '
           f'height="{height_mm}mm" viewBox="0 0 {width_mm} {height_mm}">'
           f'<path d="{path}" fill="none" stroke="#000" stroke-width="{stroke_mm}" '
           f'stroke-linecap="{cap}" stroke-linejoin="round"/></svg>')
    return render(svg.encode(), width_mm, height_mm)[..., 3] > 127


def render(svg: bytes, width_mm: float, height_mm: float) -> np.ndarray:
    """RGBA at :data:`PX_PER_MM` (resvg, the reference renderer)."""
    png = resvg_py.svg_to_bytes(svg_string=svg.decode(), width=round(width_mm * PX_PER_MM),
                                height=round(height_mm * PX_PER_MM), dpi=PX_PER_MM * 25.4)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGBA"))


def colour_mask(rgba: np.ndarray, colour: str, colours: list[str]) -> np.ndarray:
    """Where the drawing is inked in ``colour`` (the nearest of ``colours``)."""
    palette = np.array([[int(c[i:i + 2], 16) for i in (1, 3, 5)] for c in colours], float)
    # composite over white, as on paper, then take the nearest layer colour
    alpha = rgba[..., 3:4] / 255.0
    rgb = rgba[..., :3] * alpha + 255.0 * (1.0 - alpha)
    distance = np.linalg.norm(rgb[..., None, :] - palette, axis=-1)
    nearest = np.argmin(distance, axis=-1)
    return (rgba[..., 3] > 127) & (nearest == colours.index(colour))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 1.0
