"""The JSON API's methods: one table, typed parameters, documented in ``docs/API.md``.

Each method is an ``async`` (or plain) function ``(methods, connection, params)`` registered
with :func:`method` under its JSON-RPC name, with a pydantic model for its named parameters.
Methods marked ``control`` need a connection that may control the machine. Everything that
acts on the machine goes through the same paths a sender uses: lines through the dispatcher
(``$J=``, ``$X``, ``$H``, ``$110=500``, ``fire``), realtime commands straight to the machine.
Server, status, G-code and control methods are here; settings and jobs in
:mod:`server.api.jobs`.
"""

from __future__ import annotations

import asyncio
import inspect
from collections import OrderedDict
from collections.abc import Callable, Iterable
from contextvars import ContextVar
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server import __version__
from server.api.telemetry import TOPICS
from server.errors import ERROR_MEANINGS, CommandError, Error
from server.gcode.parser import check_length
from server.kernel.control import MachineControl, halts_at_once, quickstops_at_once
from server.kernel.module import ApiMethod
from server.kernel.status import build_status, snapshot, state_text
from server.protocol.events import Realtime
from server.protocol.reports import StatusScheduler

if TYPE_CHECKING:
    from server.api.server import Connection, JsonApi

INVALID_PARAMS, METHOD_NOT_FOUND = -32602, -32601
MAX_LINES = 10_000


class RpcError(Exception):
    """A JSON-RPC level error (unknown method, bad parameters)."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.code, self.message, self.data = code, message, data


def command_error(exc: CommandError) -> tuple[int, str, dict[str, Any]]:
    """A refused command as a JSON-RPC error: the code is Grbl's (or motiond's) number."""
    meaning = ERROR_MEANINGS.get(exc.code, "")
    return (
        exc.code,
        f"error:{exc.code} {exc.message or meaning}".strip(),
        {"grbl_error": exc.code, "meaning": meaning},
    )


class Params(BaseModel):
    """Named parameters: unknown names are refused, and so are NaN and infinities (JSON
    ``NaN``, ``Infinity`` or ``1e400``) in every number."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


Handler = Callable[["Methods", "Connection", Any], Any]


@dataclass(frozen=True, slots=True)
class MethodSpec:
    name: str
    handler: Handler
    params: type[BaseModel]
    control: bool


class MethodTable(dict[str, MethodSpec]):
    """JSON-RPC methods by name; each API module fills its own and the API composes them."""

    def method(
        self, name: str, params: type[Params] = Params, control: bool = False
    ) -> Callable[[Handler], Handler]:
        """Decorator: ``handler`` answers the method ``name``."""

        def add(handler: Handler) -> Handler:
            self.add(name, handler, params, control)
            return handler

        return add

    def add(
        self,
        name: str,
        handler: Handler,
        params: type[BaseModel] = Params,
        control: bool = False,
    ) -> None:
        if name in self:
            raise ValueError(f"JSON-RPC method {name} is defined twice")
        self[name] = MethodSpec(name, handler, params, control)


CORE_METHODS = MethodTable()  # server.*, machine.*, gcode.*
method = CORE_METHODS.method


# The stop generation the JSON-RPC request being handled arrived in (each request is handled in
# a task of its own: see server.api.server), read by every line it submits.
_REQUEST_TICKET: ContextVar[int | None] = ContextVar("request_ticket", default=None)


class Methods:
    """The API's view of one kernel; holds the toolpath cache."""

    def __init__(self, api: JsonApi, table: MethodTable) -> None:
        self.api = api
        self.table = table
        self.kernel = api.kernel
        self.machine = api.kernel.machine
        self.toolpaths: OrderedDict[tuple[Any, ...], dict[str, Any]] = OrderedDict()
        self.toolpath_lock = asyncio.Lock()
        self.drawing_lock = asyncio.Lock()  # one drawing import at a time
        self.material_lock = asyncio.Lock()  # one change of the material library at a time

    async def call(self, connection: Connection, name: str, params: Any) -> Any:
        spec = self.table.get(name)
        if spec is None:
            raise RpcError(METHOD_NOT_FOUND, f"method not found: {name}")
        if spec.control and not connection.can_control:
            raise CommandError(Error.AUTH_REQUIRED, "this connection may not control the machine")
        if params is None:
            params = {}
        if not isinstance(params, dict):
            raise RpcError(INVALID_PARAMS, "params must be an object (named parameters)")
        try:
            parsed = spec.params.model_validate(params)
        except ValidationError as exc:
            problems = [
                f"{'.'.join(map(str, e['loc'])) or 'params'}: {e['msg']}" for e in exc.errors()
            ]
            raise RpcError(INVALID_PARAMS, "invalid params: " + "; ".join(problems)) from exc
        token = _REQUEST_TICKET.set(self.kernel.status.ticket())  # this request's, at arrival
        try:
            result = spec.handler(self, connection, parsed)
            if inspect.isawaitable(result):
                result = await result
        finally:
            _REQUEST_TICKET.reset(token)
        return result

    async def submit(self, connection: Connection, line: str) -> list[str]:
        """One line through the dispatcher, in order with this connection's other lines,
        with the stop ticket of the request it is part of: a stop after the request arrived
        refuses its lines still to run (error 45), whatever they waited for."""
        async with connection.gcode_lock:
            return await self.kernel.dispatcher.submit(line, connection, _REQUEST_TICKET.get())

    def state(self) -> dict[str, Any]:
        return {"state": state_text(self.kernel)}

    def file_changed(self, action: str, name: str) -> None:
        self.api.publisher.broadcast(
            "job", "notify_filelist_changed", {"action": action, "file": {"name": name}}
        )


# -- server -----------------------------------------------------------------------------------
@method("server.info")
def server_info(m: Methods, connection: Connection, params: Params) -> dict[str, Any]:
    core = m.kernel.config.core
    return {
        "name": "motiond",
        "version": __version__,
        "machine": core.machine.name,
        "axes": [
            {
                "name": name.upper(),
                "min_mm": axis.min_mm,
                "max_mm": axis.max_mm,
                "max_rate_mm_min": axis.max_rate_mm_s * 60.0,
            }
            for name, axis in core.axes.items()
        ],
        "laser_mode": core.machine.laser_mode,
        "features": sorted(m.kernel.features),
        "max_s": m.machine.settings.values().get(30, 1000.0),
        "modules": sorted(m.kernel.modules),
        "commands": m.kernel.dispatcher.names(),
        "can_control": connection.can_control,
        "auth_required": m.api.http.token is not None,
        "status_rate_hz": round(1.0 / m.api.publisher.period_s, 3),
        "upload": {"url": "/upload", "max_bytes": core.jobs.max_upload_bytes},
        "methods": sorted(m.table),
        "topics": sorted(TOPICS),
    }


class AuthParams(Params):
    token: str


@method("server.auth", AuthParams)
def server_auth(m: Methods, connection: Connection, params: AuthParams) -> dict[str, Any]:
    """Present the token: control from now on. An observer connection (``?mode=observe``)
    never controls, whatever it presents: open another connection to control."""
    if connection.observer:
        raise CommandError(Error.AUTH_REQUIRED, "an observer connection never controls the machine")
    if not m.api.token_ok(params.token):
        raise CommandError(Error.AUTH_REQUIRED, "wrong token")
    connection.authenticate()
    return {"can_control": connection.can_control}


# -- status -----------------------------------------------------------------------------------
@method("machine.status")
def machine_status(m: Methods, connection: Connection, params: Params) -> dict[str, Any]:
    return build_status(m.kernel)


Topic = Literal["status", "telemetry", "console", "job"]
ALL_TOPICS: list[Topic] = ["console", "job", "status", "telemetry"]


class TopicParams(Params):
    topics: list[Topic] = Field(default_factory=lambda: list(ALL_TOPICS))


@method("machine.subscribe", TopicParams)
def machine_subscribe(m: Methods, connection: Connection, params: TopicParams) -> dict[str, Any]:
    m.api.publisher.subscribe(connection.channel, set(params.topics))
    return {"topics": sorted(connection.channel.topics), "status": build_status(m.kernel)}


@method("machine.unsubscribe", TopicParams)
def machine_unsubscribe(m: Methods, connection: Connection, params: TopicParams) -> dict[str, Any]:
    m.api.publisher.unsubscribe(connection.channel, set(params.topics))
    return {"topics": sorted(connection.channel.topics)}


# -- G-code -----------------------------------------------------------------------------------
class GcodeParams(Params):
    lines: str | list[str]
    stop_on_error: bool = True


@method("gcode.send", GcodeParams)
async def gcode_send(m: Methods, connection: Connection, params: GcodeParams) -> dict[str, Any]:
    lines = params.lines.splitlines() if isinstance(params.lines, str) else params.lines
    if len(lines) > MAX_LINES:
        raise RpcError(INVALID_PARAMS, f"at most {MAX_LINES} lines per call; upload a job instead")
    results: list[dict[str, Any]] = []
    for line in lines:
        if connection.closing:
            break
        result = await _one_line(m, connection, line)
        results.append(result)
        if "error" in result and params.stop_on_error:
            break
    return {"results": results, "skipped": len(lines) - len(results)}


_REALTIME = {"!": Realtime.HOLD, "~": Realtime.RESUME, "\x18": Realtime.RESET,
             "\x85": Realtime.JOG_CANCEL}


async def _one_line(m: Methods, connection: Connection, line: str) -> dict[str, Any]:
    limit = m.kernel.config.core.protocol.line_limit
    try:
        check_length(line, limit)  # error 11, as on every stream; nothing parsed
    except CommandError as exc:
        return _refused(line[:limit] + "...", exc)  # not echoed whole
    text = line.strip()
    if text == "?":
        report = StatusScheduler().report(
            snapshot(m.kernel, m.kernel.config.core.protocol.rx_buffer_bytes)
        )
        return {"line": line, "reply": "ok", "messages": [report]}
    try:
        if text in _REALTIME:
            if not connection.can_control:
                raise CommandError(
                    Error.AUTH_REQUIRED, "this connection may not control the machine"
                )
            m.kernel.control.realtime(_REALTIME[text])
            messages: list[str] = []
        else:
            if halts_at_once(text) and connection.can_control:
                m.kernel.control.emergency_stop()
                _REQUEST_TICKET.set(m.kernel.status.ticket())  # the stop's own line runs
            elif quickstops_at_once(text) and connection.can_control:
                m.kernel.control.quickstop()
                _REQUEST_TICKET.set(m.kernel.status.ticket())
            messages = await m.submit(connection, line)
    except CommandError as exc:
        return _refused(line, exc)
    return {"line": line, "reply": "ok", "messages": messages}


def _refused(line: str, exc: CommandError) -> dict[str, Any]:
    code, message, data = command_error(exc)
    return {
        "line": line,
        "reply": f"error:{code}",
        "messages": [],
        "error": {"code": code, "message": message, "meaning": data["meaning"]},
    }


# -- realtime control: the same MachineControl as every line session ----------------------
REALTIME_METHODS: dict[str, Callable[[MachineControl], None]] = {
    "hold": MachineControl.hold,
    "resume": MachineControl.resume,
    "reset": MachineControl.reset,
    "jog_cancel": MachineControl.jog_cancel,
    "estop": MachineControl.emergency_stop,
}


def _realtime_handler(action: Callable[[MachineControl], None]) -> Handler:
    def handler(m: Methods, connection: Connection, params: Params) -> dict[str, Any]:
        action(m.kernel.control)
        return m.state()

    return handler


for _name, _action in REALTIME_METHODS.items():
    CORE_METHODS.add(f"machine.{_name}", _realtime_handler(_action), control=True)


@method("machine.unlock", control=True)
async def machine_unlock(m: Methods, connection: Connection, params: Params) -> dict[str, Any]:
    await m.submit(connection, "$X")
    return m.state()


class HomeParams(Params):
    axes: str = Field("", pattern=r"^[XYZABCxyzabc]*$")


@method("machine.home", HomeParams, control=True)
async def machine_home(m: Methods, connection: Connection, params: HomeParams) -> dict[str, Any]:
    messages = await m.submit(connection, f"$H{params.axes.upper()}")
    return {**m.state(), "messages": messages}


class JogParams(Params):
    x: float | None = None
    y: float | None = None
    z: float | None = None
    a: float | None = None
    b: float | None = None
    c: float | None = None
    feed_mm_min: float = Field(gt=0)
    relative: bool = True


@method("machine.jog", JogParams, control=True)
async def machine_jog(m: Methods, connection: Connection, params: JogParams) -> dict[str, Any]:
    words = [
        f"{axis.upper()}{value:.4f}"
        for axis, value in params.model_dump(include=set("xyzabc")).items()
        if value is not None
    ]
    if not words:
        raise RpcError(INVALID_PARAMS, "invalid params: give at least one axis distance")
    mode = "G91" if params.relative else "G90"
    await m.submit(connection, f"$J=G21 {mode} {' '.join(words)} F{params.feed_mm_min:g}")
    return m.state()


class OverrideParams(Params):
    feed: int | None = Field(None, ge=10, le=200)
    rapid: Literal[25, 50, 100] | None = None
    spindle: int | None = Field(None, ge=10, le=200)


@method("machine.override", OverrideParams, control=True)
def machine_override(m: Methods, connection: Connection, params: OverrideParams) -> dict[str, Any]:
    m.machine.set_overrides(feed=params.feed, rapid=params.rapid, spindle=params.spindle)
    return {
        "feed": m.machine.feed_override,
        "rapid": m.machine.rapid_override,
        "spindle": m.machine.spindle_override,
    }


class _Caller:
    """A module method's view of the calling connection (implements ApiCaller)."""

    def __init__(self, m: Methods, connection: Connection) -> None:
        self._m, self._connection = m, connection

    async def submit(self, line: str) -> list[str]:
        return await self._m.submit(self._connection, line)


def _module_handler(method: ApiMethod) -> Handler:
    async def handler(m: Methods, connection: Connection, params: Any) -> Any:
        return await method.handler(params, _Caller(m, connection))

    return handler


def compose(*tables: MethodTable, modules: Iterable[ApiMethod] = ()) -> MethodTable:
    """The API's whole method table: the core tables, then what modules contribute."""
    composed = MethodTable()
    for table in tables:
        for spec in table.values():
            composed.add(spec.name, spec.handler, spec.params, spec.control)
    for method in modules:
        composed.add(method.name, _module_handler(method), method.params, method.control)
    return composed
