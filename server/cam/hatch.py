"""Fill: the closed shapes of a layer hatched with parallel lines, as LightBurn fills.

The region is the layer's closed shapes under the even-odd rule (a shape inside another is a
hole, an island inside a hole is filled again). Lines run at ``angle_deg`` from the X axis,
``interval_mm`` apart, centred on the scan positions ``(k + 1/2) * interval`` so that lines as
wide as the interval tile the region. Every edge is crossed with every scan line at once in
numpy (no per-line Python loop over the edges): the crossings sorted along each line pair up
into the spans inside.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from server.cam.model import Points, Shape
from server.errors import DrawingError

MAX_SPANS = 20_000_000


def hatch(shapes: list[Shape], interval_mm: float, angle_deg: float) -> list[list[Points]]:
    """The spans inside the region, per scan line in order, each span a 2x2 array (start,
    end) running in +u (the hatch direction); empty lines are left out."""
    closed = [shape.points for shape in shapes if shape.closed and len(shape.points) > 2]
    if not closed:
        return []
    turn = math.radians(angle_deg)
    cos, sin = math.cos(turn), math.sin(turn)
    rotate = np.array([[cos, -sin], [sin, cos]])  # scan frame (u, v) -> drawing (x, y)
    starts = np.concatenate([points @ rotate for points in closed])  # (x,y) -> (u,v)
    ends = np.concatenate([np.roll(points, -1, axis=0) @ rotate for points in closed])
    line, u = _crossings(starts, ends, interval_mm)
    spans: list[list[Points]] = []
    if not len(line):
        return spans
    order = np.lexsort((u, line))
    line, u = line[order], u[order]
    boundaries = np.flatnonzero(np.diff(line)) + 1
    for lines_u, number in zip(np.split(u, boundaries), np.split(line, boundaries), strict=True):
        v = (number[0] + 0.5) * interval_mm
        pairs = lines_u[: len(lines_u) // 2 * 2].reshape(-1, 2)
        pairs = pairs[pairs[:, 1] - pairs[:, 0] > 1e-9]
        if len(pairs):
            spans.append([_back(pair, v, rotate) for pair in pairs])
    return spans


def _crossings(
    starts: np.ndarray, ends: np.ndarray, interval_mm: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Every (scan line number, u) where an edge crosses a scan line, half-open in v so a
    vertex on a line counts once."""
    v0, v1 = starts[:, 1], ends[:, 1]
    low, high = np.minimum(v0, v1), np.maximum(v0, v1)
    first = np.ceil(low / interval_mm - 0.5).astype(np.int64)
    last = np.ceil(high / interval_mm - 0.5).astype(np.int64)  # exclusive
    count = np.maximum(last - first, 0)
    total = int(count.sum())
    if total > MAX_SPANS:
        raise DrawingError(f"fill: {total:,} line crossings, over {MAX_SPANS:,}: "
                           "a coarser interval or a smaller drawing")
    edge = np.repeat(np.arange(len(count)), count)
    offset = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
    line = first[edge] + offset
    v = (line + 0.5) * interval_mm
    t = (v - v0[edge]) / (v1[edge] - v0[edge])
    u = starts[edge, 0] + t * (ends[edge, 0] - starts[edge, 0])
    return line, u


def _back(pair: np.ndarray, v: float, rotate: np.ndarray) -> Points:
    scan = np.array([[pair[0], v], [pair[1], v]])
    return np.asarray(scan @ rotate.T, dtype=np.float64)
