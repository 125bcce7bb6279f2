"""The JSON API's drawing methods (:data:`DRAWING_METHODS`): a drawing in, a stored job out.

``drawing.read`` gives a dropped file's layers, their default settings and a preview to draw
over the machine's travel; ``drawing.generate`` makes the job with each layer's settings and
stores it through the job store, as an upload would be, so placement, the fit check, frame,
the estimate, the toolpath preview and progress work on it unchanged. Both run
:mod:`server.cam` in a worker process (:mod:`.drawing_worker`: bounded in time and memory)
and push ``notify_drawing_progress`` to the ``job`` topic. See ``docs/API.md``.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
from dataclasses import asdict
from pathlib import PurePath
from typing import TYPE_CHECKING, Any

from pydantic import Field

from server.api import drawing_worker
from server.api.methods import INVALID_PARAMS, Methods, MethodTable, Params, RpcError
from server.errors import CommandError, DrawingError, Error

if TYPE_CHECKING:
    from server.api.server import Connection

DRAWING_METHODS = MethodTable()
method = DRAWING_METHODS.method
CAM_PACKAGES = ("svgelements", "ezdxf", "PIL", "shapely")


class DrawingParams(Params):
    name: str = Field(min_length=1, max_length=200)
    base64: str | None = Field(None, min_length=1)
    file: str | None = Field(None, min_length=1, max_length=200)  # a file in the job store
    width_mm: float | None = Field(None, gt=0, le=10_000)
    dpi: float | None = Field(None, ge=1, le=10_000)


class GenerateParams(DrawingParams):
    layers: dict[str, dict[str, Any]] = Field(default_factory=dict)
    order: list[str] = Field(default_factory=list, max_length=256)  # layers cut first, in turn
    job: str | None = Field(None, min_length=1, max_length=200)


async def _data(m: Methods, params: DrawingParams) -> bytes:
    """The drawing's bytes: inline (``base64``, for files that fit an /api message) or a file
    sent to ``POST /upload`` before (``file``)."""
    if (params.base64 is None) == (params.file is None):
        raise RpcError(INVALID_PARAMS, "invalid params: give exactly one of base64 and file")
    if params.file is not None:
        path = m.kernel.jobs.path(params.file)
        try:
            return await asyncio.to_thread(path.read_bytes)
        except OSError as exc:
            raise CommandError(Error.FILE_ERROR, f"no file {path.name}") from exc
    try:
        return base64.b64decode(params.base64 or "", validate=True)
    except binascii.Error as exc:
        raise RpcError(INVALID_PARAMS, "invalid params: base64: not valid base64") from exc


def _check_extra() -> None:
    import importlib.util

    missing = [name for name in CAM_PACKAGES if importlib.util.find_spec(name) is None]
    if missing:
        raise CommandError(Error.FILE_ERROR, f"drawing import needs {', '.join(missing)}: "
                           "pip install 'motiond[cam]'")


async def _run(m: Methods, task: str, name: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    _check_extra()

    def progress(fraction: float) -> None:
        m.api.publisher.broadcast("job", "notify_drawing_progress",
                                  {"name": name, "task": task, "fraction": round(fraction, 3)})

    async with m.drawing_lock:  # one import at a time: each may take a core and its memory
        try:
            return await drawing_worker.run(task, kwargs, progress)
        except DrawingError as exc:
            raise CommandError(Error.FILE_ERROR, str(exc)) from exc


@method("drawing.read", DrawingParams, control=True)
async def drawing_read(m: Methods, connection: Connection,
                       params: DrawingParams) -> dict[str, Any]:
    return await _run(m, "read", params.name, {
        "data": await _data(m, params), "name": params.name, "width_mm": params.width_mm,
        "dpi": params.dpi})


@method("drawing.generate", GenerateParams, control=True)
async def drawing_generate(m: Methods, connection: Connection,
                           params: GenerateParams) -> dict[str, Any]:
    result = await _run(m, "generate", params.name, {
        "data": await _data(m, params), "name": params.name, "width_mm": params.width_mm,
        "dpi": params.dpi, "layers": params.layers, "order": params.order,
        "max_s": m.kernel.config.laser_max_s()})
    job = params.job or f"{PurePath(params.name).stem}.gcode"
    stored = await m.kernel.jobs.save(job, result["gcode"])  # written in a thread
    m.file_changed("upload", stored.name)
    return {"job": asdict(stored), "lines": result["lines"], "drawing": result["drawing"]}
