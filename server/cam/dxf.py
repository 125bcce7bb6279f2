"""DXF to layers, with ezdxf.

The model space's LINE, ARC, CIRCLE, ELLIPSE, LWPOLYLINE and POLYLINE (bulges included) and
SPLINE entities, and those inside block references (INSERT, with their transforms), become
polylines within :data:`TOLERANCE_MM` (ezdxf's ``make_path`` and ``flattening``), scaled to mm
by the header's ``$INSUNITS`` (unitless: mm) and moved so the drawing's lower-left corner is
at 0,0; pieces whose ends meet are joined (:mod:`.chain`). One layer per colour (the
entity's, or its DXF layer's when BYLAYER; ACI 7, white on a black screen, is black on the
material). Annotations (text, dimensions, hatches, points,
images) are skipped with a warning; any other entity is refused, naming its type and handle.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from server.cam.chain import joined
from server.cam.model import Drawing, Layer, LayerSettings, Shape
from server.errors import DrawingError

TOLERANCE_MM = 0.01
MAX_BYTES = 32 << 20
MAX_ENTITIES = 200_000
MAX_POINTS = 4_000_000
MAX_BLOCK_DEPTH = 8
CUT = frozenset({"LINE", "ARC", "CIRCLE", "ELLIPSE", "LWPOLYLINE", "POLYLINE", "SPLINE"})
SKIPPED = frozenset({"TEXT", "MTEXT", "DIMENSION", "ARC_DIMENSION", "LEADER", "MLEADER",
                     "MULTILEADER", "HATCH", "MPOLYGON", "POINT", "IMAGE", "WIPEOUT",
                     "ATTRIB", "ATTDEF", "VIEWPORT", "SOLID", "TRACE", "XLINE", "RAY"})


def read_dxf(data: bytes, name: str) -> Drawing:
    """The drawing in ``data``, one layer per colour.

    Raises:
        DrawingError: not a DXF ezdxf reads, an unknown entity, or over the bounds.
    """
    from ezdxf import recover
    from ezdxf.lldxf.const import DXFError

    if len(data) > MAX_BYTES:
        raise DrawingError(f"{name}: {len(data):,} bytes, over the {MAX_BYTES:,} a DXF may have")
    try:
        doc, _auditor = recover.read(io.BytesIO(data))
    except (DXFError, OSError, ValueError, UnicodeDecodeError) as exc:
        raise DrawingError(f"{name}: not a readable DXF: {exc}") from exc
    scale = _mm_per_unit(doc)
    reader = _Reader(doc, name, scale)
    for entity in doc.modelspace():
        reader.add(entity, 0)
    return reader.drawing()


def _mm_per_unit(doc: Any) -> float:
    from ezdxf import units
    from ezdxf.enums import InsertUnits

    code = int(doc.header.get("$INSUNITS", 0))
    if code == 0:
        return 1.0
    try:
        unit = InsertUnits(code)
        return float(units.conversion_factor(unit, InsertUnits.Millimeters))
    except ValueError as exc:
        raise DrawingError(f"$INSUNITS {code}: not a unit motiond knows") from exc


class _Reader:
    def __init__(self, doc: Any, name: str, scale: float) -> None:
        self.doc, self.name, self.scale = doc, name, scale
        self.layers: dict[str, list[Shape]] = {}
        self.skipped: dict[str, int] = {}
        self.entities = self.points = 0

    def add(self, entity: Any, depth: int) -> None:
        kind = entity.dxftype()
        self.entities += 1
        if self.entities > MAX_ENTITIES:
            raise DrawingError(f"{self.name}: more than {MAX_ENTITIES:,} entities")
        if kind == "INSERT":
            if depth >= MAX_BLOCK_DEPTH:
                raise DrawingError(f"{self.name}: INSERT #{entity.dxf.handle}: blocks nested "
                                   f"deeper than {MAX_BLOCK_DEPTH}")
            for child in entity.virtual_entities():
                self.add(child, depth + 1)
        elif kind in CUT:
            self._add_curve(entity)
        elif kind in SKIPPED:
            self.skipped[kind] = self.skipped.get(kind, 0) + 1
        else:
            raise DrawingError(f"{self.name}: entity {kind} #{entity.dxf.get('handle', '?')} "
                               f"on layer {entity.dxf.get('layer', '0')!r} is not one motiond "
                               "cuts (lines, arcs, circles, ellipses, polylines, splines)")

    def _add_curve(self, entity: Any) -> None:
        from ezdxf import path

        curve = path.make_path(entity)
        points = np.array([(v.x, v.y) for v in curve.flattening(TOLERANCE_MM / self.scale)],
                          dtype=np.float64) * self.scale
        self.points += len(points)
        if self.points > MAX_POINTS:
            raise DrawingError(f"{self.name}: entity {entity.dxftype()} "
                               f"#{entity.dxf.get('handle', '?')}: over {MAX_POINTS:,} points")
        if len(points) < 2:
            return
        closed = len(points) > 3 and bool(np.allclose(points[0], points[-1], atol=1e-6))
        if closed:
            points = points[:-1]
        self.layers.setdefault(self._colour(entity), []).append(Shape(points, closed))

    def _colour(self, entity: Any) -> str:
        from ezdxf import colors

        if entity.rgb is not None:
            return "#{:02x}{:02x}{:02x}".format(*entity.rgb)
        aci = int(entity.dxf.get("color", 256))
        if aci in (0, 256):  # BYBLOCK, BYLAYER
            layer = self.doc.layers.get(entity.dxf.get("layer", "0"))
            aci = abs(int(layer.color)) if layer is not None else 7
        if aci == 7:
            return "#000000"
        return "#{:02x}{:02x}{:02x}".format(*colors.aci2rgb(aci))

    def drawing(self) -> Drawing:
        shapes = [shape for group in self.layers.values() for shape in group]
        warnings = [f"{count} {kind} entit{'y' if count == 1 else 'ies'} skipped (not cut)"
                    for kind, count in sorted(self.skipped.items())]
        if not shapes:
            return Drawing(self.name, [], 0.0, 0.0, warnings)
        every = np.concatenate([shape.points for shape in shapes])
        low, high = every.min(axis=0), every.max(axis=0)
        for shape in shapes:
            shape.points = shape.points - low
        layers = [Layer(colour, LayerSettings(mode="line"), joined(group))
                  for colour, group in self.layers.items()]
        width, height = (float(v) for v in high - low)
        return Drawing(self.name, layers, width, height, warnings)
