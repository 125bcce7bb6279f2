"""Klipper's API socket framing, sans I/O: JSON objects each ended by ``\\x03``.

A request is ``{"id": ID, "method": "objects/query", "params": {...}}``; the answer carries the
same ``id`` and either ``result`` or ``error`` (``{"error": "WebRequestError", "message":
...}``). Pushed messages (subscriptions, G-code output, remote methods) have a ``method`` and
``params`` and no ``id``. :class:`Framer` takes bytes as they arrive and returns whole
requests; a request larger than its bound, or a stream that is not JSON objects, is a
:class:`FramingError` (the transport closes that connection).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

ETX = b"\x03"
MAX_REQUEST_BYTES = 1 << 20  # a gcode/script of a few thousand lines


class FramingError(Exception):
    """The peer broke the framing: too large, not JSON, or not an object."""


@dataclass(frozen=True, slots=True)
class Request:
    """One request: ``id`` is echoed back (it may be absent: None)."""

    id: Any
    method: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(slots=True)
class Framer:
    """Bytes in, :class:`Request` objects out; never holds more than ``limit_bytes``."""

    limit_bytes: int = MAX_REQUEST_BYTES
    _buffer: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[Request]:
        self._buffer += data
        *whole, rest = bytes(self._buffer).split(ETX)
        if len(rest) > self.limit_bytes:
            raise FramingError(f"a request larger than {self.limit_bytes} bytes")
        self._buffer = bytearray(rest)
        return [parse_request(chunk) for chunk in whole if chunk.strip()]


def parse_request(chunk: bytes) -> Request:
    if len(chunk) > MAX_REQUEST_BYTES:
        raise FramingError(f"a request larger than {MAX_REQUEST_BYTES} bytes")
    try:
        data = json.loads(chunk)
    except (ValueError, UnicodeDecodeError) as exc:
        raise FramingError(f"not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise FramingError("a request is not a JSON object")
    method, params = data.get("method"), data.get("params", {})
    if not isinstance(method, str) or not isinstance(params, dict):
        return Request(data.get("id"), "", {"_invalid": True})
    return Request(data.get("id"), method, params)


def encode(message: dict[str, Any]) -> bytes:
    """One message on the wire (NaN and Infinity are not JSON: refused)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False).encode() + ETX


def result(request_id: Any, value: dict[str, Any]) -> dict[str, Any]:
    return {"id": request_id, "result": value}


def error(request_id: Any, message: str) -> dict[str, Any]:
    return {"id": request_id, "error": {"error": "WebRequestError", "message": message}}


def push(template: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """A pushed message: the subscriber's ``response_template`` with ``params`` set."""
    return {**template, "params": params}
