"""The material library: named sets of layer settings, kept per machine (a JSON file in its
data folder, read and written by the callers: the API in a thread, the CLI at once).

A material maps layer names (``#ff0000``, ``image``) to settings (any subset of
:class:`~server.cam.model.LayerSettings`, validated on the way in and out). Applied to a
drawing, each of its layers with a name in the material takes those settings; the others keep
theirs. Sans I/O: text in, text out.
"""

from __future__ import annotations

import json
from typing import Any

from server.cam.model import SHORT_NAMES, Drawing, layer_settings
from server.errors import DrawingError

MAX_MATERIALS = 200
MAX_LAYERS = 64
MAX_NAME = 100

Library = dict[str, dict[str, dict[str, Any]]]  # material -> layer -> settings


def parse_library(text: str, where: str = "materials") -> Library:
    """The library in ``text`` (empty text: none), every setting checked.

    Raises:
        DrawingError: not the library's JSON, or a setting out of bounds (naming it).
    """
    if not text.strip():
        return {}
    try:
        raw = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DrawingError(f"{where}: not JSON: {exc}") from exc
    if not isinstance(raw, dict) or not isinstance(raw.get("materials"), dict):
        raise DrawingError(f"{where}: expected {{\"materials\": {{NAME: {{LAYER: settings}}}}}}")
    library: Library = {}
    for name, layers in raw["materials"].items():
        library = with_material(library, name, layers)
    return library


def with_material(library: Library, name: str, layers: Any) -> Library:
    """``library`` with material ``name`` set to ``layers`` (validated), as a new dict."""
    name = str(name).strip()
    if not name or len(name) > MAX_NAME:
        raise DrawingError(f"material {name!r}: a name of 1 to {MAX_NAME} characters")
    if not isinstance(layers, dict) or len(layers) > MAX_LAYERS:
        raise DrawingError(f"material {name!r}: up to {MAX_LAYERS} layers, each NAME: settings")
    checked: dict[str, dict[str, Any]] = {}
    for layer, values in layers.items():
        if not isinstance(values, dict):
            raise DrawingError(f"material {name!r}, layer {layer!r}: settings must be an object")
        settings = layer_settings(values, where=f"material {name!r}, layer {layer}")
        fields = [SHORT_NAMES.get(str(key), str(key)) for key in values]
        checked[str(layer)] = {field: getattr(settings, field) for field in fields}
    if name not in library and len(library) >= MAX_MATERIALS:
        raise DrawingError(f"material {name!r}: the library holds {MAX_MATERIALS} at most")
    return {**library, name: checked}


def dump_library(library: Library) -> str:
    return json.dumps({"materials": library}, indent=2, sort_keys=True) + "\n"


def apply_material(drawing: Drawing, library: Library, name: str) -> None:
    """Each layer of ``drawing`` named in material ``name`` takes its settings.

    Raises:
        DrawingError: no such material.
    """
    if name not in library:
        known = ", ".join(sorted(library)) or "none"
        raise DrawingError(f"no material {name!r} (materials: {known})")
    for layer in drawing.layers:
        values = library[name].get(layer.name)
        if values is not None:
            layer.settings = layer_settings(values, layer.settings, where=f"layer {layer.name}")
