"""The JSON API's material library (:data:`MATERIAL_METHODS`): named layer settings kept in
the machine's data folder (:func:`server.paths.materials_path`), read and written in a
thread, one change at a time. The rules are :mod:`server.cam.materials`."""

from __future__ import annotations

import asyncio
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import Field

from server.api.methods import Methods, MethodTable, Params
from server.cam.materials import Library, dump_library, parse_library, with_material
from server.errors import CommandError, DrawingError, Error
from server.paths import materials_path

if TYPE_CHECKING:
    from server.api.server import Connection

MATERIAL_METHODS = MethodTable()
method = MATERIAL_METHODS.method


class NameParams(Params):
    name: str = Field(min_length=1, max_length=100)


class SaveParams(NameParams):
    layers: dict[str, dict[str, Any]]


def _read(path: Path) -> Library:
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {}
    return parse_library(text, str(path))


def _write(path: Path, library: Library) -> None:
    """Atomically: a temporary file beside it, then renamed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp = tempfile.mkstemp(dir=path.parent, prefix=".materials-")
    with os.fdopen(handle, "w") as stream:
        stream.write(dump_library(library))
    os.replace(temp, path)


async def _library(m: Methods) -> Library:
    try:
        return await asyncio.to_thread(_read, materials_path(m.kernel.config.core))
    except DrawingError as exc:
        raise CommandError(Error.FILE_ERROR, str(exc)) from exc


@method("material.list")
async def material_list(m: Methods, connection: Connection, params: Params) -> Library:
    return await _library(m)


@method("material.save", SaveParams, control=True)
async def material_save(m: Methods, connection: Connection, params: SaveParams) -> Library:
    async with m.material_lock:
        try:
            library = with_material(await _library(m), params.name, params.layers)
        except DrawingError as exc:
            raise CommandError(Error.FILE_ERROR, str(exc)) from exc
        await asyncio.to_thread(_write, materials_path(m.kernel.config.core), library)
    return library


@method("material.delete", NameParams, control=True)
async def material_delete(m: Methods, connection: Connection, params: NameParams) -> Library:
    async with m.material_lock:
        library = await _library(m)
        if params.name not in library:
            raise CommandError(Error.FILE_ERROR, f"no material {params.name!r}")
        library = {name: layers for name, layers in library.items() if name != params.name}
        await asyncio.to_thread(_write, materials_path(m.kernel.config.core), library)
    return library
