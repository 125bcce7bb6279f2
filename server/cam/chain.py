"""Open pieces joined end to end into longer polylines, and closed when they come round.

CAD draws a slot as two lines and two arcs, a DXF outline often as loose segments: joined,
they become the closed shapes that containment (inner first) and fills need. Ends meet when
they are within ``tolerance_mm`` (snapped to a grid of that size, so the join is O(n)).
"""

from __future__ import annotations

import numpy as np

from server.cam.model import Shape

Key = tuple[int, int]


def joined(shapes: list[Shape], tolerance_mm: float = 1e-3) -> list[Shape]:
    """``shapes`` with the open ones joined where their ends meet."""
    closed = [shape for shape in shapes if shape.closed]
    pieces = [shape.points for shape in shapes if not shape.closed]
    ends: dict[Key, list[int]] = {}
    for index, points in enumerate(pieces):
        for point in (points[0], points[-1]):
            ends.setdefault(_key(point, tolerance_mm), []).append(index)
    used = [False] * len(pieces)
    result = list(closed)
    for index in range(len(pieces)):
        if used[index]:
            continue
        used[index] = True
        chain = _grow(pieces[index], pieces, ends, used, tolerance_mm)
        chain = _grow(chain[::-1], pieces, ends, used, tolerance_mm)
        is_closed = len(chain) > 3 and bool(np.hypot(*(chain[0] - chain[-1])) <= tolerance_mm)
        result.append(Shape(chain[:-1] if is_closed else chain, is_closed))
    return result


def _grow(chain: np.ndarray, pieces: list[np.ndarray], ends: dict[Key, list[int]],
          used: list[bool], tolerance_mm: float) -> np.ndarray:
    parts = [chain]
    tail = chain[-1]
    while True:
        candidates = [i for i in ends.get(_key(tail, tolerance_mm), ()) if not used[i]]
        if not candidates:
            break
        index = candidates[0]
        used[index] = True
        points = pieces[index]
        if _key(points[0], tolerance_mm) != _key(tail, tolerance_mm):
            points = points[::-1]
        parts.append(points[1:])
        tail = points[-1]
    return np.concatenate(parts) if len(parts) > 1 else chain


def _key(point: np.ndarray, tolerance_mm: float) -> Key:
    return round(float(point[0]) / tolerance_mm), round(float(point[1]) / tolerance_mm)
