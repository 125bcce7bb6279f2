"""What the web UI draws before a job is made: each layer's shapes over the machine's travel.

:func:`describe` is the drawing's description (:meth:`Drawing.describe`) with, per layer,
its shapes as flat ``[x0, y0, x1, y1, ...]`` lists in mm (every k-th point, so the whole
preview stays under ``max_points``; a shape keeps its ends) and, for an image, a small PNG
(``thumbnail``, base64, at most :data:`THUMBNAIL_PX` on its longer side).
"""

from __future__ import annotations

import base64
import io
from typing import Any

import numpy as np

from server.cam.model import Drawing, Layer

THUMBNAIL_PX = 256


MAX_POINTS = 6000  # enough to see the shapes; encoded as JSON on the server's loop in ~2 ms


def describe(drawing: Drawing, max_points: int = MAX_POINTS) -> dict[str, Any]:
    total = sum(len(shape.points) for layer in drawing.layers for shape in layer.shapes)
    step = max(1, -(-total // max_points))
    described = drawing.describe()
    for layer, row in zip(drawing.layers, described["layers"], strict=True):
        row["paths"] = [_decimated(shape.points, shape.closed, step) for shape in layer.shapes]
        row["thumbnail"] = _thumbnail(layer)
    return described


def _decimated(points: np.ndarray, closed: bool, step: int) -> list[float]:
    kept = points[::step]
    if step > 1 and len(points) > 1:
        kept = np.vstack([kept, points[-1:]])
    if closed:
        kept = np.vstack([kept, kept[:1]])
    return [float(v) for v in np.round(kept, 2).ravel()]


def _thumbnail(layer: Layer) -> str | None:
    if layer.raster is None:
        return None
    from PIL import Image

    gray = (layer.raster.gray * 255.0).clip(0, 255).astype(np.uint8)
    image = Image.fromarray(gray, mode="L")
    image.thumbnail((THUMBNAIL_PX, THUMBNAIL_PX))
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()
