"""SVG to layers, with svgelements (the parser MeerK40t and vpype use).

svgelements applies groups' transforms, the viewBox and physical units (``width="100mm"``)
and turns basic shapes into paths; here each path is cut into straight pieces within
:data:`TOLERANCE_MM` of the curve and sorted into layers: its stroke colour's (mode line)
and its fill colour's (mode fill). Text is not cut: it must be converted to paths first, and
a warning says so. Embedded images are skipped with a warning (import them as images).

Hostile input is refused before svgelements sees it (:func:`check_source`): entity
declarations (expansion bombs, external entities), more than :data:`MAX_BYTES`, more than
:data:`MAX_ELEMENTS` elements, or a path or polyline of more than :data:`MAX_PATH_NUMBERS`
coordinates (the whole file: :data:`MAX_NUMBERS`), each error naming the element's line.
"""

from __future__ import annotations

import functools
import io
import math
import re
from typing import Any

import numpy as np

from server.cam.model import Drawing, Layer, LayerSettings, Shape
from server.errors import DrawingError

MM_PER_PX = 25.4 / 96.0  # svgelements' user unit at 96 ppi, as browsers and Inkscape
TOLERANCE_MM = 0.01
MAX_BYTES = 32 << 20
MAX_ELEMENTS = 200_000
MAX_PATH_NUMBERS = 1_000_000  # a path of 500,000 points
MAX_NUMBERS = 4_000_000
MAX_PIECES_PER_CURVE = 1000
_ENTITY = re.compile(rb"<!ENTITY", re.IGNORECASE)
_POINTS = re.compile(rb"\s(?:d|points)\s*=\s*(?:\"[^\"]*\"|'[^']*')")


def check_source(data: bytes, name: str) -> None:
    """Refuse what would make the parser expand, fetch or grow without bound.

    Raises:
        DrawingError: naming the rule broken and the line it was broken on.
    """
    if len(data) > MAX_BYTES:
        raise DrawingError(f"{name}: {len(data):,} bytes, over the {MAX_BYTES:,} an SVG may have")
    entity = _ENTITY.search(data)
    if entity is not None:
        raise DrawingError(f"{name}, line {_line(data, entity.start())}: entity declarations "
                           "(<!ENTITY>) are refused: they can expand without bound or read "
                           "other files")
    if data.count(b"<") > MAX_ELEMENTS:
        raise DrawingError(f"{name}: more than {MAX_ELEMENTS:,} elements")
    total = 0
    for match in _POINTS.finditer(data):
        numbers = _count_numbers(data, match.start(), match.end())
        if numbers > MAX_PATH_NUMBERS:
            raise DrawingError(
                f"{name}, line {_line(data, match.start())}: a path of over "
                f"{MAX_PATH_NUMBERS // 2:,} points, more than one path may have")
        total += numbers
        if total > MAX_NUMBERS:
            raise DrawingError(f"{name}, line {_line(data, match.start())}: over "
                               f"{MAX_NUMBERS // 2:,} points in the paths so far")


def _count_numbers(data: bytes, start: int, end: int) -> int:
    """How many numbers ``data[start:end]`` holds (runs of digits and dots; an exponent
    counts twice, an upper bound), a megabyte at a time in numpy."""
    count, previous = 0, False
    for chunk_start in range(start, end, 1 << 20):
        chunk = np.frombuffer(data, np.uint8, min(1 << 20, end - chunk_start), chunk_start)
        digit = ((chunk >= 48) & (chunk <= 57)) | (chunk == 46)
        count += int(np.count_nonzero(digit[1:] & ~digit[:-1])) + int(digit[0] and not previous)
        previous = bool(digit[-1])
    return count


def _line(data: bytes, offset: int) -> int:
    return data.count(b"\n", 0, offset) + 1


def read_svg(data: bytes, name: str) -> Drawing:
    """The drawing in ``data``, one layer per stroke or fill colour, in order of appearance.

    Raises:
        DrawingError: refused input (:func:`check_source`) or XML the parser cannot read.
    """
    import svgelements as se

    check_source(data, name)
    try:
        svg = se.SVG.parse(io.BytesIO(data), reify=True, ppi=96.0)
    except Exception as exc:  # the parser's errors have no common base: ParseError, ValueError
        raise DrawingError(f"{name}: not a readable SVG: {exc}") from exc
    height_mm = float(svg.height or 0.0) * MM_PER_PX
    width_mm = float(svg.width or 0.0) * MM_PER_PX
    layers: dict[str, Layer] = {}
    warnings: list[str] = []
    texts = images = 0
    for index, element in enumerate(svg.elements()):
        if isinstance(element, se.Text):
            texts += 1
        elif isinstance(element, se.Image):
            images += 1
        elif isinstance(element, se.Shape) and _visible(element):
            _add_shape(element, layers, height_mm, group=index)
    if texts:
        warnings.append(f"{texts} text element(s) not cut: convert text to paths first "
                        "(Inkscape: Path > Object to Path)")
    if images:
        warnings.append(f"{images} embedded image(s) skipped: import images as PNG or JPEG")
    return Drawing(name, list(layers.values()), width_mm, height_mm, warnings)


def _visible(element: Any) -> bool:
    values = element.values
    return bool(values.get("visibility") != "hidden" and values.get("display") != "none")


def _add_shape(element: Any, layers: dict[str, Layer], height_mm: float, group: int) -> None:
    """The element's subpaths into its stroke colour's layer and its fill colour's; for the
    fill, as one region (``group``) under the element's fill rule."""
    stroke, fill = _colour(element.stroke), _colour(element.fill)
    if not (element.stroke_width or 0.0) > 0.0:  # stroke-width="0" draws no stroke
        stroke = None
    if stroke is None and fill is None:
        return
    shapes = _flatten(element, height_mm)
    if not shapes:
        return
    wanted = {fill: "fill"} if fill is not None else {}
    if stroke is not None:
        wanted[stroke] = "line"  # stroked and filled in one colour: cut it by default
    for colour, mode in wanted.items():
        layer = layers.get(colour)
        if layer is None:
            layer = layers[colour] = Layer(colour, LayerSettings(mode=mode))
        elif mode == "line" and layer.settings.mode == "fill":
            layer.settings = layer.settings.model_copy(update={"mode": "line"})
        if mode == "fill":  # a fill closes its subpaths
            nonzero = element.values.get("fill-rule", "nonzero") != "evenodd"
            layer.shapes.extend(Shape(s.points, len(s.points) > 2, group, nonzero)
                                for s in shapes)
        else:
            layer.shapes.extend(shapes)


def _colour(colour: Any) -> str | None:
    if colour is None or colour.value is None or colour.alpha == 0:
        return None
    return str(colour.hexrgb)


def _flatten(element: Any, height_mm: float) -> list[Shape]:
    """The element's subpaths as polylines in mm, Y up."""
    import svgelements as se

    path = element if isinstance(element, se.Path) else se.Path(element)
    shapes: list[Shape] = []
    for subpath in path.as_subpaths():
        points: list[tuple[float, float]] = []
        closed = False
        for segment in subpath:
            if isinstance(segment, se.Move):
                points.append((segment.end.x, segment.end.y))
            elif isinstance(segment, se.Close):
                closed = True
            elif segment.start is not None and segment.end is not None:
                points += _segment_points(segment, se)
        if not points:
            continue
        array = np.array(points, dtype=np.float64) * MM_PER_PX
        array[:, 1] = height_mm - array[:, 1]
        shapes.extend(_shape(array, closed))
    return shapes


def _shape(points: np.ndarray, closed: bool) -> list[Shape]:
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(points, axis=0)) > 1e-9, axis=1)
    points = points[keep]
    if len(points) > 2 and np.allclose(points[0], points[-1], atol=1e-9):
        points, closed = points[:-1], True
    if len(points) < 2:
        return []
    return [Shape(points, closed and len(points) > 2)]


def _segment_points(segment: Any, se: Any) -> list[tuple[float, float]]:
    """The points after the segment's start (its end included), within the tolerance: lines
    as they are, Béziers evaluated in numpy, arcs by svgelements."""
    end = segment.end
    if isinstance(segment, se.Line):
        return [(end.x, end.y)]
    if isinstance(segment, se.CubicBezier):
        controls: tuple[Any, ...] = (segment.start, segment.control1, segment.control2, end)
    elif isinstance(segment, se.QuadraticBezier):
        controls = (segment.start, segment.control, end)
    else:
        count = _arc_pieces(segment, se)
        positions = np.linspace(0.0, 1.0, count + 1)[1:]
        return [(x, y) for x, y in np.asarray(segment.npoint(positions)).tolist()]
    xs = [float(p.x) for p in controls]
    ys = [float(p.y) for p in controls]
    count = _bezier_pieces(xs, ys)
    if count == 1:
        return [(end.x, end.y)]
    weights = _bernstein(len(controls) - 1, count)
    return list(zip((weights @ xs).tolist(), (weights @ ys).tolist(), strict=True))


@functools.lru_cache(maxsize=2048)
def _bernstein(degree: int, count: int) -> np.ndarray:
    """The Bézier weights of the control points at ``t = 1/count .. 1`` (rows)."""
    t = np.linspace(0.0, 1.0, count + 1)[1:, None]
    return np.hstack([math.comb(degree, k) * t**k * (1.0 - t) ** (degree - k)
                      for k in range(degree + 1)])


def _bezier_pieces(xs: list[float], ys: list[float]) -> int:
    """Pieces that keep a Bézier within :data:`TOLERANCE_MM`: its chord error after n pieces
    is at most ``d (d-1) / 8 * max|second difference| / n²`` for degree d."""
    degree = len(xs) - 1
    bend = max(math.hypot(xs[k] - 2 * xs[k + 1] + xs[k + 2], ys[k] - 2 * ys[k + 1] + ys[k + 2])
               for k in range(degree - 1))
    count = math.sqrt(degree * (degree - 1) / 8.0 * bend / (TOLERANCE_MM / MM_PER_PX))
    return max(1, min(MAX_PIECES_PER_CURVE, math.ceil(count)))


def _arc_pieces(segment: Any, se: Any) -> int:
    """Pieces that keep an arc within :data:`TOLERANCE_MM` (of its larger radius)."""
    if not isinstance(segment, se.Arc):
        return 16
    radius = max(abs(segment.rx), abs(segment.ry), 1e-9)
    step = 2.0 * math.acos(max(-1.0, 1.0 - TOLERANCE_MM / MM_PER_PX / radius))
    count = float(abs(segment.sweep)) / max(step, 1e-6)
    return max(1, min(MAX_PIECES_PER_CURVE, math.ceil(count)))
