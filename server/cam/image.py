"""PNG and JPEG to an image layer, with Pillow.

The physical size comes from ``width_mm`` (the height follows the aspect ratio), else from
``dpi``, else from the DPI the file carries, else 96 DPI. Transparent pixels count as white.
A file over :data:`MAX_PIXELS` pixels is refused from its header, before any pixel is
decoded (Pillow's decompression-bomb check, made an error at our own, lower limit).
"""

from __future__ import annotations

import io
import warnings

import numpy as np

from server.cam.model import Drawing, Layer, LayerSettings, Raster
from server.errors import DrawingError

MAX_PIXELS = 50_000_000
MAX_BYTES = 64 << 20
MM_PER_INCH = 25.4


def read_image(data: bytes, name: str, *, width_mm: float | None = None,
               dpi: float | None = None) -> Drawing:
    """One image layer (mode image), its bottom-left corner at 0,0.

    Raises:
        DrawingError: not an image Pillow reads, too many pixels, or a bad size.
    """
    from PIL import Image

    if len(data) > MAX_BYTES:
        raise DrawingError(f"{name}: {len(data):,} bytes, over the {MAX_BYTES:,} an image may have")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data))
            columns, rows = image.size
            if columns * rows > MAX_PIXELS:
                raise DrawingError(f"{name}: {columns:,} x {rows:,} pixels, over the "
                                   f"{MAX_PIXELS:,} an image may have")
            gray = _gray(image)
    except DrawingError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise DrawingError(f"{name}: over the {MAX_PIXELS:,} pixels an image may have "
                           f"({exc})") from exc
    except (OSError, ValueError) as exc:
        raise DrawingError(f"{name}: not an image motiond reads: {exc}") from exc
    width, height = _size_mm(image, name, width_mm, dpi)
    raster = Raster(gray, 0.0, 0.0, width, height)
    layer = Layer("image", LayerSettings(mode="image", speed_mm_min=3000.0), raster=raster)
    return Drawing(name, [layer], width, height)


def _gray(image: object) -> np.ndarray:
    """Gray 0..1 (float32), transparency over white."""
    from PIL import Image

    assert isinstance(image, Image.Image)
    if image.mode in ("RGBA", "LA", "PA", "P") or "transparency" in image.info:
        background = Image.new("RGBA", image.size, (255, 255, 255, 255))
        image = Image.alpha_composite(background, image.convert("RGBA"))
    return np.asarray(image.convert("L"), dtype=np.float32) / 255.0


def _size_mm(image: object, name: str, width_mm: float | None,
             dpi: float | None) -> tuple[float, float]:
    from PIL import Image

    assert isinstance(image, Image.Image)
    columns, rows = image.size
    if width_mm is not None:
        if not 0.0 < width_mm <= 10_000.0:
            raise DrawingError(f"{name}: width {width_mm} mm: give 0 < width <= 10000")
        return width_mm, width_mm * rows / columns
    if dpi is None:
        found = image.info.get("dpi", (96.0, 96.0))
        dpi = float(found[0]) if found and float(found[0]) > 1.0 else 96.0
    if not 1.0 <= dpi <= 10_000.0:
        raise DrawingError(f"{name}: {dpi} DPI: give 1 to 10000")
    return columns * MM_PER_INCH / dpi, rows * MM_PER_INCH / dpi
