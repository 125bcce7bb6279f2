"""The drawing as the importers leave it, and each layer's settings.

A :class:`Drawing` holds :class:`Layer` s; a layer holds polylines (:class:`Shape`, mm, Y up)
or one raster (:class:`Raster`), and the :class:`LayerSettings` it will be cut with. The
settings are a pydantic model so that the CLI's ``--layer`` option, the JSON API and the
material library are validated by one set of bounds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.errors import DrawingError

Points = npt.NDArray[np.float64]  # (n, 2): x, y in mm
Mode = Literal["line", "fill", "image"]
Dither = Literal["grayscale", "threshold", "floyd-steinberg", "jarvis", "stucki"]
MAX_SPEED_MM_MIN = 120_000.0


class LayerSettings(BaseModel):
    """How one layer is cut. Power is in percent of the laser's maximum S (M4: the power
    follows the speed, so ``power_pct`` is reached at ``speed_mm_min``); an image's gray
    levels map onto ``min_power_pct .. power_pct``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Mode = "line"
    speed_mm_min: float = Field(default=1000.0, gt=0.0, le=MAX_SPEED_MM_MIN)
    power_pct: float = Field(default=50.0, ge=0.0, le=100.0)
    min_power_pct: float = Field(default=0.0, ge=0.0, le=100.0)
    passes: int = Field(default=1, ge=1, le=100)
    interval_mm: float = Field(default=0.1, ge=0.01, le=10.0)
    angle_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    overscan_mm: float = Field(default=2.0, ge=0.0, le=50.0)
    bidirectional: bool = True
    dither: Dither = "grayscale"
    enabled: bool = True


# The short names the CLI's --layer option takes, and the field each stands for.
SHORT_NAMES = {
    "speed": "speed_mm_min", "power": "power_pct", "min_power": "min_power_pct",
    "interval": "interval_mm", "angle": "angle_deg", "overscan": "overscan_mm",
}


def layer_settings(values: dict[str, Any], base: LayerSettings | None = None,
                   where: str = "layer") -> LayerSettings:
    """``base`` with ``values`` (full or short names) applied, validated.

    Raises:
        DrawingError: an unknown name or a value out of bounds, naming ``where``.
    """
    merged = (base or LayerSettings()).model_dump()
    merged.update({SHORT_NAMES.get(key, key): value for key, value in values.items()})
    try:
        return LayerSettings.model_validate(merged)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in error['loc'])}: {error['msg']}" for error in exc.errors()
        )
        raise DrawingError(f"{where}: {problems}") from exc


@dataclass(slots=True)
class Shape:
    """A polyline in mm; ``closed``: its last point joins its first (not repeated).

    For a fill, the shapes of one ``group`` (the subpaths of one SVG element) make one region
    under their rule (``nonzero``, else even-odd), and the regions of a layer are united; a
    DXF's shapes are all one even-odd group (a circle inside an outline is a hole)."""

    points: Points
    closed: bool
    group: int = 0
    nonzero: bool = False


@dataclass(slots=True)
class Raster:
    """An image to engrave: ``gray`` 0 (black, full power) .. 1 (white, off), row 0 at the
    top, covering ``width_mm`` x ``height_mm`` with its bottom-left corner at ``x_mm, y_mm``."""

    gray: npt.NDArray[np.float32]
    x_mm: float
    y_mm: float
    width_mm: float
    height_mm: float


@dataclass(slots=True)
class Layer:
    """One colour's shapes (or one image) and how they are cut."""

    name: str
    settings: LayerSettings
    shapes: list[Shape] = field(default_factory=list)
    raster: Raster | None = None

    def describe(self) -> dict[str, Any]:
        """JSON-able: the name, the settings, counts and bounds (for the UI and the CLI)."""
        low, high = self.bounds_mm()
        return {
            "name": self.name, "settings": self.settings.model_dump(),
            "shapes": len(self.shapes),
            "closed": sum(1 for shape in self.shapes if shape.closed),
            "points": sum(len(shape.points) for shape in self.shapes),
            "image": None if self.raster is None else list(self.raster.gray.shape[::-1]),
            "bounds": {"min": [round(v, 3) for v in low], "max": [round(v, 3) for v in high]},
        }

    def bounds_mm(self) -> tuple[tuple[float, float], tuple[float, float]]:
        if self.raster is not None:
            r = self.raster
            return (r.x_mm, r.y_mm), (r.x_mm + r.width_mm, r.y_mm + r.height_mm)
        if not self.shapes:
            return (0.0, 0.0), (0.0, 0.0)
        every = np.concatenate([shape.points for shape in self.shapes])
        low, high = every.min(axis=0), every.max(axis=0)
        return (float(low[0]), float(low[1])), (float(high[0]), float(high[1]))


@dataclass(slots=True)
class Drawing:
    """What an importer read: its layers, its page size (mm) and what it could not use."""

    name: str
    layers: list[Layer]
    width_mm: float
    height_mm: float
    warnings: list[str] = field(default_factory=list)

    def layer(self, name: str) -> Layer:
        for layer in self.layers:
            if layer.name.lower() == name.lower():
                return layer
        names = ", ".join(layer.name for layer in self.layers) or "none"
        raise DrawingError(f"{self.name}: no layer {name!r} (layers: {names})")

    def reorder(self, names: list[str]) -> None:
        """The layers named first, in that order; the others after them as they were.

        Raises:
            DrawingError: a name that is not a layer's.
        """
        first = [self.layer(name) for name in names]
        self.layers = first + [layer for layer in self.layers if layer not in first]

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name, "width_mm": round(self.width_mm, 3),
            "height_mm": round(self.height_mm, 3),
            "layers": [layer.describe() for layer in self.layers], "warnings": self.warnings,
        }


def parse_layer_option(text: str) -> tuple[str, dict[str, str]]:
    """``NAME:key=value,key=value`` (the CLI's ``--layer``) as the name and its values;
    the values stay text for pydantic to convert and check.

    Raises:
        DrawingError: no ``:``, or an item without ``=``.
    """
    name, colon, rest = text.partition(":")
    if not colon or not name.strip():
        raise DrawingError(f"--layer {text!r}: give NAME:key=value,... (NAME a colour "
                           "such as #ff0000, or image)")
    values: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in rest.split(","))):
        key, equals, value = item.partition("=")
        if not equals:
            raise DrawingError(f"--layer {text!r}: {item!r} is not key=value")
        values[key.strip()] = value.strip()
    return name.strip(), values


def apply_layer_options(drawing: Drawing, options: dict[str, dict[str, Any]]) -> None:
    """Each named layer's settings updated with its values (validated, errors name it)."""
    for name, values in options.items():
        layer = drawing.layer(name)
        layer.settings = layer_settings(values, layer.settings, where=f"layer {layer.name}")
