"""Fill: the closed shapes of a layer hatched with parallel lines, as LightBurn fills.

The region is, as an SVG renderer fills it, the union of the layer's groups (one per SVG
element), each the closed shapes of the group under its rule: even-odd (a shape inside
another is a hole, an island in a hole is filled again) or nonzero (by winding). Lines run at
``angle_deg`` from the X axis, ``interval_mm`` apart, centred on the scan positions
``(k + 1/2) * interval`` so that lines as wide as the interval tile the region. Every edge is
crossed with every scan line at once in numpy (no per-line Python loop over the edges); the
crossings sorted along each line and group give where the group is inside, and the spans of
the groups on one line are merged.
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
    closed = [shape for shape in shapes if shape.closed and len(shape.points) > 2]
    if not closed:
        return []
    turn = math.radians(angle_deg)
    cos, sin = math.cos(turn), math.sin(turn)
    rotate = np.array([[cos, -sin], [sin, cos]])  # scan frame (u, v) -> drawing (x, y)
    starts = np.concatenate([shape.points @ rotate for shape in closed])  # (x,y) -> (u,v)
    ends = np.concatenate([np.roll(shape.points, -1, axis=0) @ rotate for shape in closed])
    sizes = [len(shape.points) for shape in closed]
    groups = np.repeat([shape.group for shape in closed], sizes)
    nonzero = np.repeat([shape.nonzero for shape in closed], sizes)
    edge, line, u = _crossings(starts, ends, interval_mm)
    if not len(line):
        return []
    order = np.lexsort((u, groups[edge], line))
    edge, line, u = edge[order], line[order], u[order]
    upward = np.where(ends[edge, 1] > starts[edge, 1], 1, -1)
    entering, leaving = _transitions(line, groups[edge], upward, nonzero[edge])
    return _merged(line[entering], u[entering], u[leaving], interval_mm, rotate)


def _transitions(line: np.ndarray, group: np.ndarray, upward: np.ndarray,
                 nonzero: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The crossings (sorted by line, group, u) where a group's region starts and ends: the
    count (even-odd) or the winding (nonzero) of the crossings before, within the run of one
    line and group, going from outside to inside and back."""
    run_start = np.ones(len(line), dtype=bool)
    run_start[1:] = (np.diff(line) != 0) | (np.diff(group) != 0)
    run_id = np.cumsum(run_start) - 1
    first_of_run = np.flatnonzero(run_start)
    index = np.arange(len(line))
    count = index - first_of_run[run_id] + 1  # crossings so far, this one included
    winding = np.cumsum(upward)
    winding = winding - (winding[first_of_run] - upward[first_of_run])[run_id]
    inside_after = np.where(nonzero, winding != 0, count % 2 == 1)
    inside_before = np.zeros(len(line), dtype=bool)
    inside_before[1:] = inside_after[:-1]
    inside_before[run_start] = False
    return np.flatnonzero(inside_after & ~inside_before), np.flatnonzero(~inside_after
                                                                          & inside_before)


def _merged(line: np.ndarray, begin: np.ndarray, end: np.ndarray, interval_mm: float,
            rotate: np.ndarray) -> list[list[Points]]:
    """The groups' intervals on each line united, as spans in the drawing's frame."""
    order = np.lexsort((begin, line))
    spans: list[list[Points]] = []
    current_line, low, high = None, 0.0, 0.0
    row: list[Points] = []
    for number, a, b in zip(line[order].tolist(), begin[order].tolist(), end[order].tolist(),
                            strict=True):
        if number != current_line or a > high:
            if current_line is not None and high - low > 1e-9:
                row.append(_back((low, high), (current_line + 0.5) * interval_mm, rotate))
            if number != current_line and row:
                spans.append(row)
                row = []
            current_line, low, high = number, a, b
        else:
            high = max(high, b)
    if current_line is not None and high - low > 1e-9:
        row.append(_back((low, high), (current_line + 0.5) * interval_mm, rotate))
    if row:
        spans.append(row)
    return spans


def _crossings(
    starts: np.ndarray, ends: np.ndarray, interval_mm: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Every (edge, scan line number, u) where an edge crosses a scan line, half-open in v so
    a vertex on a line counts once."""
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
    return edge, line, u


def _back(pair: tuple[float, float], v: float, rotate: np.ndarray) -> Points:
    scan = np.array([[pair[0], v], [pair[1], v]])
    return np.asarray(scan @ rotate.T, dtype=np.float64)
