"""The order a layer's shapes are cut in: inner shapes before the closed shape that contains
them (a part never drops out before its holes are cut), and among the shapes free to go next,
the nearest to where the head is (greedy nearest neighbour). A closed shape starts at its
vertex nearest the head, an open one at its nearer end.

Containment comes from shapely's STRtree (``contains`` on every closed shape at once). The
greedy search is exact up to :data:`EXACT_LIMIT` shapes (a numpy distance per pick, O(n²));
beyond it the candidates come from a grid of cells around the head, still nearest first.
"""

from __future__ import annotations

import numpy as np

from server.cam.model import Points, Shape


def containment(shapes: list[Shape]) -> list[list[int]]:
    """For each shape, the indices of the shapes it contains (only closed shapes contain).

    B contains A when A's bounding box lies within B's and A's probe points (up to
    :data:`PROBES` vertices) are all inside B's outline (even-odd, so a self-crossing
    outline needs no repair first). The boxes are paired by shapely's STRtree, the points
    tested by ``shapely.contains_xy`` on prepared polygons, all at once.
    """
    import shapely

    inside: list[list[int]] = [[] for _ in shapes]
    closed = [i for i, shape in enumerate(shapes) if shape.closed and len(shape.points) > 2]
    if not closed:
        return inside
    lows = np.array([shape.points.min(axis=0) for shape in shapes])
    highs = np.array([shape.points.max(axis=0) for shape in shapes])
    boxes = shapely.box(lows[:, 0], lows[:, 1], highs[:, 0], highs[:, 1])
    tree = shapely.STRtree(boxes[closed])
    children, slots = tree.query(boxes, predicate="covered_by")
    parents = np.asarray(closed)[slots]
    keep = children != parents
    children, parents = children[keep], parents[keep]
    if not len(children):
        return inside
    polygons = np.array([shapely.Polygon(shape.points) if shape.closed and len(shape.points) > 2
                         else None for shape in shapes], dtype=object)
    shapely.prepare(polygons[closed])
    probes = [_probe_points(shape) for shape in shapes]
    count = np.array([len(probes[c]) for c in children])
    points = np.concatenate([probes[c] for c in children])
    owners = np.repeat(np.arange(len(children)), count)
    hit = shapely.contains_xy(polygons[parents[owners]], points[:, 0], points[:, 1])
    all_inside = np.logical_and.reduceat(hit, np.concatenate([[0], np.cumsum(count)[:-1]]))
    for child, parent in zip(children[all_inside].tolist(), parents[all_inside].tolist(),
                             strict=True):
        if not _same_outline(shapes[parent], shapes[child]):
            inside[parent].append(child)
    return inside


def _same_outline(a: Shape, b: Shape) -> bool:
    return a.points.shape == b.points.shape and bool(np.allclose(a.points, b.points))


def cut_order(shapes: list[Shape], start_mm: tuple[float, float] = (0.0, 0.0)) -> list[Points]:
    """The shapes as polylines in cutting order (a closed one ends where it started)."""
    if not shapes:
        return []
    contains = containment(shapes)
    waiting = np.array([len(children) for children in contains])  # uncut shapes inside
    parents: list[list[int]] = [[] for _ in shapes]
    for parent, children in enumerate(contains):
        for child in children:
            parents[child].append(parent)
    picker = _Picker(shapes)
    for free in np.flatnonzero(waiting == 0).tolist():
        picker.offer(free)
    head = np.array(start_mm, dtype=float)
    ordered: list[Points] = []
    while picker.ready:
        index = picker.take_nearest(head)
        path = _oriented(shapes[index], head)
        ordered.append(path)
        head = path[-1]
        for parent in parents[index]:
            waiting[parent] -= 1
            if waiting[parent] == 0:
                picker.offer(parent)
    return ordered


def _oriented(shape: Shape, head: np.ndarray) -> Points:
    points = shape.points
    if shape.closed:
        first = int(np.argmin(np.sum((points - head) ** 2, axis=1)))
        rolled = np.roll(points, -first, axis=0)
        return np.vstack([rolled, rolled[:1]])
    if np.sum((points[-1] - head) ** 2) < np.sum((points[0] - head) ** 2):
        return points[::-1]
    return points


class _Picker:
    """The shapes free to be cut, and the nearest of them to a point: by either end of an open
    shape, by up to :data:`PROBES` vertices of a closed one. Probes sit in a grid of cells
    holding a few shapes each; the search widens ring by ring around the head and stops one
    ring after the first hit (a nearer probe may lie only in the next ring)."""

    def __init__(self, shapes: list[Shape]) -> None:
        probes = [_probe_points(shape) for shape in shapes]
        self._points = np.concatenate(probes)
        self._owner = np.repeat(np.arange(len(shapes)), [len(p) for p in probes])
        self._ready = np.zeros(len(shapes), dtype=bool)
        self._count = 0
        low, high = self._points.min(axis=0), self._points.max(axis=0)
        area = float(np.prod(np.maximum(high - low, 1e-3)))
        self._cell = max(1e-3, (area * 4.0 / len(shapes)) ** 0.5)
        self._low = low
        keys = np.floor((self._points - low) / self._cell).astype(np.int64)
        self._span = int(keys.max()) + 1
        self._cells: dict[tuple[int, int], list[int]] = {}
        for probe, (cx, cy) in enumerate(keys.tolist()):
            self._cells.setdefault((cx, cy), []).append(probe)

    @property
    def ready(self) -> bool:
        return self._count > 0

    def offer(self, index: int) -> None:
        self._ready[index] = True
        self._count += 1

    def take_nearest(self, head: np.ndarray) -> int:
        cx, cy = (int(v) for v in np.floor((head - self._low) / self._cell))
        best, best_d2, found_ring = -1, np.inf, -1
        for ring in range(self._span + abs(cx) + abs(cy) + 2):
            probes = [p for key in _ring(cx, cy, ring) for p in self._cells.get(key, ())]
            if probes:
                index = np.array(probes)
                index = index[self._ready[self._owner[index]]]
                if len(index):
                    d2 = np.sum((self._points[index] - head) ** 2, axis=1)
                    pick = int(np.argmin(d2))
                    if d2[pick] < best_d2:
                        best, best_d2 = int(self._owner[index[pick]]), float(d2[pick])
                        found_ring = ring if found_ring < 0 else found_ring
            if found_ring >= 0 and ring >= found_ring + 1:
                break
        self._ready[best] = False
        self._count -= 1
        return best


def _ring(cx: int, cy: int, ring: int) -> list[tuple[int, int]]:
    if ring == 0:
        return [(cx, cy)]
    cells = [(cx + dx, cy + dy) for dx in range(-ring, ring + 1) for dy in (-ring, ring)]
    cells += [(cx + dx, cy + dy) for dx in (-ring, ring) for dy in range(-ring + 1, ring)]
    return cells


PROBES = 16


def _probe_points(shape: Shape) -> np.ndarray:
    if not shape.closed:
        return shape.points[[0, -1]]
    step = max(1, len(shape.points) // PROBES)
    return shape.points[::step]
