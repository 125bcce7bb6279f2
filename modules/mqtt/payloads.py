"""What goes over the broker (pure: no I/O): control requests, their replies, the status.

Requests are JSON objects (UTF-8) on ``<prefix>/cmd/<command>``; ``id`` (a string of at most
128 characters, or an integer) comes back in every reply on ``<prefix>/reply``:

- ``cmd/gcode``: ``{"id": "a1", "lines": ["G0 X10", "G1 X20 F600"]}`` (or one string with
  line breaks); each line is answered once, with its ``index``;
- ``cmd/realtime``: ``{"id": "a2", "command": "hold"}`` (``hold``, ``resume``, ``reset``), or
  the bare word ``hold`` (Home Assistant buttons), answered with ``id`` null;
- ``cmd/job``: ``{"id": "a3", "name": "part.nc"}``: start a stored job.

Anything else (not UTF-8, not JSON, unknown or missing keys, wrong types, control characters
in a line, too many lines) is refused as a whole with one reply (``reason``
``invalid_payload``), and changes nothing.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, StrictStr, ValidationError

REALTIME = ("hold", "resume", "reset")
CorrelationId = Annotated[StrictStr, Field(max_length=128)] | StrictInt
_CONTROL = re.compile("[\x00-\x08\x0a-\x1f\x7f-\x9f]")
STATUS_KEYS = ("state", "alarm", "mpos", "wpos", "speed_mm_min", "power_pct", "tool",
               "queue_depth", "line", "overrides", "job")


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class GcodeRequest(_Request):
    id: CorrelationId
    lines: list[StrictStr] | StrictStr


class RealtimeRequest(_Request):
    id: CorrelationId | None = None
    command: Literal["hold", "resume", "reset"]


class JobRequest(_Request):
    id: CorrelationId
    name: StrictStr = Field(min_length=1, max_length=200)


@dataclass(frozen=True, slots=True)
class Gcode:
    id: str | int
    lines: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Realtime:
    id: str | int | None
    command: str


@dataclass(frozen=True, slots=True)
class StartJob:
    id: str | int
    name: str


@dataclass(frozen=True, slots=True)
class Invalid:
    """A refused payload: ``id`` when one could be read, and why."""

    id: str | int | None
    message: str


Request = Gcode | Realtime | StartJob


def parse_request(command: str, payload: bytes, max_lines: int) -> Request | Invalid:
    """The request on ``cmd/<command>``, or why it is refused."""
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError:
        return Invalid(None, "the payload is not UTF-8")
    if command == "realtime" and text.strip() in REALTIME:
        return Realtime(None, text.strip())
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        return Invalid(None, f"cmd/{command} takes a JSON object")
    if not isinstance(data, dict):
        return Invalid(None, f"cmd/{command} takes a JSON object")
    try:
        return _build(command, data, max_lines)
    except ValidationError as exc:
        return Invalid(correlation_id(data), _first_error(exc))
    except ValueError as exc:
        return Invalid(correlation_id(data), str(exc))


def _build(command: str, data: dict[str, Any], max_lines: int) -> Request:
    if command == "gcode":
        gcode = GcodeRequest.model_validate(data)
        lines = gcode.lines.splitlines() if isinstance(gcode.lines, str) else gcode.lines
        return Gcode(gcode.id, check_lines(lines, max_lines))
    if command == "realtime":
        realtime = RealtimeRequest.model_validate(data)
        return Realtime(realtime.id, realtime.command)
    if command == "job":
        job = JobRequest.model_validate(data)
        return StartJob(job.id, job.name)
    raise ValueError(f"unknown command topic cmd/{command} (gcode, realtime, job)")


def check_lines(lines: list[str], max_lines: int) -> tuple[str, ...]:
    """One G-code line per item: none empty of lines, none over ``max_lines``, no control
    characters (realtime commands have their own topic)."""
    if not lines:
        raise ValueError("lines is empty")
    if len(lines) > max_lines:
        raise ValueError(f"at most {max_lines} lines per message")
    for index, line in enumerate(lines):
        if _CONTROL.search(line):
            raise ValueError(f"line {index} holds a control character or a line break")
    return tuple(lines)


def correlation_id(data: Any) -> str | int | None:
    """The request's ``id`` when it is a valid one (to answer even a refused request)."""
    value = data.get("id") if isinstance(data, dict) else None
    if isinstance(value, str) and len(value) <= 128:
        return value
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    return None


def peek_id(payload: bytes) -> str | int | None:
    """Best effort: the ``id`` of a payload that is not obeyed (control disabled)."""
    try:
        return correlation_id(json.loads(payload.decode("utf-8")))
    except (ValueError, RecursionError):
        return None


def _first_error(exc: ValidationError) -> str:
    error = exc.errors()[0]
    where = ".".join(str(part) for part in error["loc"])
    return f"{where}: {error['msg']}" if where else str(error["msg"])


# -- replies --------------------------------------------------------------------------------
def ok_reply(request_id: str | int | None, command: str, **fields: Any) -> dict[str, Any]:
    return {"id": request_id, "command": command, "ok": True, **fields}


def error_reply(
    request_id: str | int | None, command: str, reason: str, message: str,
    code: int | None = None, **fields: Any,
) -> dict[str, Any]:
    """``reason``: ``invalid_payload``, ``control_disabled``, ``busy`` or ``refused`` (the
    machine refused the command; ``code`` is its Grbl/motiond error number)."""
    error = {"reason": reason, "code": code, "message": message}
    return {"id": request_id, "command": command, "ok": False, "error": error, **fields}


def encode(payload: Any) -> bytes:
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()


# -- status ---------------------------------------------------------------------------------
def status_payload(snapshot: dict[str, Any], machine: str) -> dict[str, Any]:
    """``<prefix>/status``: the machine's JSON status (``ModuleContext.status()``), cut to
    what a dashboard shows, with the programmed feed beside the speed."""
    modal = snapshot.get("modal") or {}
    return {
        "machine": machine,
        **{key: snapshot.get(key) for key in STATUS_KEYS},
        "feed_mm_min": modal.get("feed_mm_min"),
    }
