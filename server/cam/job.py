"""The whole way from a file's bytes to G-code: :func:`read_drawing` then :func:`make_job`.

Layers are cut in :func:`default_order` (engravings, then cuts from the innermost; a
layer may be disabled), each pass of a layer after the one before; within a layer, line mode
cuts the shapes in :func:`~server.cam.order.cut_order` (inner first, nearest next), fill mode
hatches the region line by line (:mod:`.hatch`), image mode engraves (:mod:`.raster`). ``progress``
is called with a fraction 0..1 after each layer's pass, for a bar or a pushed status.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import PurePath

import numpy as np

from server.cam.emit import Program
from server.cam.hatch import hatch
from server.cam.model import Drawing, Layer, LayerSettings
from server.cam.order import cut_order
from server.errors import DrawingError

KINDS = {".svg": "svg", ".dxf": "dxf", ".png": "image", ".jpg": "image", ".jpeg": "image"}


def read_drawing(data: bytes, name: str, *, width_mm: float | None = None,
                 dpi: float | None = None) -> Drawing:
    """The drawing in ``data``; its kind from the name's suffix (.svg, .dxf, .png, .jpg),
    its layers in :func:`default_order`. ``width_mm``/``dpi`` size an image (default: the
    DPI it carries, else 96).

    Raises:
        DrawingError: an unknown kind, or what the importer refused.
    """
    drawing = _read(data, name, width_mm, dpi)
    drawing.layers = default_order(drawing.layers)
    return drawing


def default_order(layers: list[Layer]) -> list[Layer]:
    """Engravings first (image, fill), then the line layers from the smallest extent to the
    largest: an outline that holds the rest is cut last, after everything inside it, as
    within a layer. Otherwise the drawing's order (the sort is stable)."""
    def key(layer: Layer) -> tuple[int, float]:
        if layer.settings.mode != "line":
            return (0, 0.0)
        (x0, y0), (x1, y1) = layer.bounds_mm()
        return (1, (x1 - x0) * (y1 - y0))

    return sorted(layers, key=key)


def _read(data: bytes, name: str, width_mm: float | None, dpi: float | None) -> Drawing:
    kind = KINDS.get(PurePath(name).suffix.lower())
    if kind == "svg":
        from server.cam.svg import read_svg

        return read_svg(data, name)
    if kind == "dxf":
        from server.cam.dxf import read_dxf

        return read_dxf(data, name)
    if kind == "image":
        from server.cam.image import read_image

        return read_image(data, name, width_mm=width_mm, dpi=dpi)
    raise DrawingError(f"{name}: not a drawing motiond reads (.svg, .dxf, .png, .jpg)")


def make_job(drawing: Drawing, max_s: float = 1000.0,
             progress: Callable[[float], None] | None = None) -> str:
    """The G-code of every enabled layer of ``drawing``; ``max_s`` is the laser's S for
    full power (Grbl's $30).

    Raises:
        DrawingError: nothing to cut, or a layer too large to make.
    """
    program = Program(drawing.name, max_s)
    layers = [layer for layer in drawing.layers if layer.settings.enabled]
    if not any(layer.shapes or layer.raster is not None for layer in layers):
        raise DrawingError(f"{drawing.name}: nothing to cut (no enabled layer has shapes)")
    steps = sum(layer.settings.passes for layer in layers)
    done = 0
    for layer in layers:
        for number in range(1, layer.settings.passes + 1):
            _layer_pass(program, layer, number)
            done += 1
            if progress is not None:
                progress(done / steps)
    return program.finish()


def _layer_pass(program: Program, layer: Layer, number: int) -> None:
    settings = layer.settings
    program.comment(f"layer {layer.name}: {settings.mode}, {settings.speed_mm_min:g} mm/min, "
                    f"{settings.power_pct:g} %, pass {number} of {settings.passes}")
    program.start_layer(settings.speed_mm_min)
    if settings.mode == "image" or layer.raster is not None:
        if layer.raster is None:
            raise DrawingError(f"layer {layer.name}: image mode needs an image")
        from server.cam.raster import engrave

        engrave(program, layer.raster, settings)
    elif settings.mode == "fill":
        _fill(program, layer, settings)
    else:
        head = program.position()
        for path in cut_order(layer.shapes, head):
            program.polyline(path, settings.power_pct)


def _fill(program: Program, layer: Layer, settings: LayerSettings) -> None:
    lines = hatch(layer.shapes, settings.interval_mm, settings.angle_deg)
    if not lines:
        raise DrawingError(f"layer {layer.name}: fill mode needs closed shapes")
    overscan = settings.overscan_mm
    forward = True
    for spans in lines:
        ordered = spans if forward else [span[::-1] for span in reversed(spans)]
        for span in ordered:
            start, end = span[0], span[1]
            direction = (end - start) / max(float(np.hypot(*(end - start))), 1e-12)
            before = start - direction * overscan
            program.travel(float(before[0]), float(before[1]))
            if overscan:
                program.cut_to(float(start[0]), float(start[1]), 0.0)
            program.cut_to(float(end[0]), float(end[1]), settings.power_pct)
            if overscan:
                after = end + direction * overscan
                program.cut_to(float(after[0]), float(after[1]), 0.0)
        forward = not forward if settings.bidirectional else True
