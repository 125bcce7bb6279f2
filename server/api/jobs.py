"""The JSON API's settings and job methods (:data:`JOB_METHODS`, composed by the API).

Imported by :mod:`server.api.server`; see ``docs/API.md`` for the reference.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
from dataclasses import asdict
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import Field

from server.api.methods import INVALID_PARAMS, Handler, Methods, MethodTable, Params, RpcError
from server.errors import CommandError, Error
from server.gcode.interpreter import Interpreter
from server.kernel.status import job_dict
from server.offline.estimate import file_lines
from server.offline.toolpath import plan_toolpath

if TYPE_CHECKING:
    from server.api.server import Connection
    from server.config import CoreConfig

JOB_METHODS = MethodTable()  # settings.* and job.*
method = JOB_METHODS.method
TOOLPATH_CACHE = 2  # results kept (each at most max_segments long): the latest file versions


# -- settings ---------------------------------------------------------------------------------
@method("settings.list")
def settings_list(m: Methods, connection: Connection, params: Params) -> list[dict[str, Any]]:
    settings = m.machine.settings
    values = settings.values()
    return [
        {
            "number": number,
            "value": values[number],
            "description": setting.description,
            "writable": setting.write is not None,
        }
        for number, setting in sorted(settings.table.items())
    ]


class SettingParams(Params):
    number: int = Field(ge=0)
    value: float  # finite: Params refuses NaN and infinities


@method("settings.set", SettingParams, control=True)
async def settings_set(m: Methods, connection: Connection, params: SettingParams) -> dict[str, Any]:
    value = format(Decimal(repr(params.value)), "f")  # every digit, never an exponent
    await m.submit(connection, f"${params.number}={value}")
    return {"number": params.number, "value": m.machine.settings.values()[params.number]}


# -- jobs -------------------------------------------------------------------------------------
class NameParams(Params):
    name: str = Field(min_length=1, max_length=255)


class UploadParams(NameParams):
    text: str | None = None
    base64: str | None = None


class ToolpathParams(NameParams):
    max_segments: int = Field(50_000, ge=100, le=200_000)


@method("job.list")
def job_list(m: Methods, connection: Connection, params: Params) -> list[dict[str, Any]]:
    return [asdict(file) for file in m.kernel.jobs.files()]


@method("job.upload", UploadParams, control=True)
async def job_upload(m: Methods, connection: Connection, params: UploadParams) -> dict[str, Any]:
    if (params.text is None) == (params.base64 is None):
        raise RpcError(INVALID_PARAMS, "invalid params: give exactly one of text and base64")
    try:
        data = (
            params.text.encode()
            if params.text is not None
            else base64.b64decode(params.base64 or "", validate=True)
        )
    except binascii.Error as exc:
        raise RpcError(INVALID_PARAMS, "invalid params: base64: not valid base64") from exc
    stored = await m.kernel.jobs.save(params.name, data)
    m.file_changed("upload", stored.name)
    return asdict(stored)


@method("job.delete", NameParams, control=True)
async def job_delete(m: Methods, connection: Connection, params: NameParams) -> dict[str, Any]:
    await m.kernel.jobs.delete(params.name)
    m.file_changed("delete", params.name)
    return {"deleted": params.name}


def _progress(m: Methods) -> dict[str, Any] | None:
    progress = m.kernel.jobs.progress()
    return None if progress is None else job_dict(progress)


@method("job.start", NameParams, control=True)
async def job_start(
    m: Methods, connection: Connection, params: NameParams
) -> dict[str, Any] | None:
    await m.kernel.jobs.start(params.name)  # error 47 when it does not fit the travel
    return _progress(m)


def _job_handler(action: str) -> Handler:
    def handler(m: Methods, connection: Connection, params: Params) -> dict[str, Any] | None:
        getattr(m.kernel.jobs, action)()
        return _progress(m)

    return handler


for _name, _job_action in (("pause", "suspend"), ("resume", "resume"), ("abort", "abort")):
    JOB_METHODS.add(f"job.{_name}", _job_handler(_job_action), control=True)


@method("job.progress")
def job_progress(m: Methods, connection: Connection, params: Params) -> dict[str, Any] | None:
    return _progress(m)


@method("job.toolpath", ToolpathParams)
async def job_toolpath(
    m: Methods, connection: Connection, params: ToolpathParams
) -> dict[str, Any]:
    path = m.kernel.jobs.path(params.name)
    try:
        info = await asyncio.to_thread(path.stat)
    except OSError as exc:
        raise CommandError(Error.FILE_ERROR, f"no job file {path.name}") from exc
    key = (path.name, info.st_size, info.st_mtime_ns, params.max_segments)
    async with m.toolpath_lock:  # one planning thread at a time
        cached = m.toolpaths.get(key)
        if cached is None:
            core = m.kernel.config.core.model_copy(deep=True)
            core.machine.soft_limits = False  # preview in work coordinates, whatever the WCS
            interpreter = m.machine.new_interpreter(soft_limits=False)
            cached = await asyncio.to_thread(
                _plan_file, path, core, params.max_segments, interpreter
            )
            m.toolpaths[key] = cached
            while len(m.toolpaths) > TOOLPATH_CACHE:
                m.toolpaths.popitem(last=False)
        m.toolpaths.move_to_end(key)
    return {"name": path.name, **cached}


def _plan_file(
    path: Path, core: CoreConfig, max_segments: int, interpreter: Interpreter
) -> dict[str, Any]:
    """plan_toolpath on the file's lines, read as the planning goes (in this thread)."""
    try:
        with path.open(errors="replace") as handle:
            lines = file_lines(handle, core.protocol.line_limit)
            return plan_toolpath(lines, core, max_segments, interpreter)
    except OSError as exc:
        raise CommandError(Error.FILE_ERROR, f"cannot read {path.name}: {exc.strerror}") from exc
