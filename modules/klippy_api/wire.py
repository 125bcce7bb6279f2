"""Klipper's API socket framing, sans I/O: JSON objects each ended by ``\\x03``.

A request is ``{"id": ID, "method": "objects/query", "params": {...}}``; the answer carries the
same ``id`` and either ``result`` or ``error`` (``{"error": "WebRequestError", "message":
...}``). Pushed messages (subscriptions, G-code output, remote methods) have a ``method`` and
``params`` and no ``id``.

:class:`Framer` takes bytes as they arrive (:meth:`Framer.push`) and gives back one request at
a time (:meth:`Framer.pop`), so the caller decides how many it handles in one go; each byte is
searched for the end mark once. Two kinds of fault:

- a stream that is not JSON objects, or a request larger than its bound, is a
  :class:`FramingError`: the peer does not speak the protocol and the transport closes it;
- a JSON object that is not a valid request (numbers that are not finite, as ``NaN``,
  ``Infinity``, ``1e999``, or integers of more than 19 digits; nesting deeper than the
  decoder's recursion bound; an id that is not a number or a string; a method that is not a
  string) is a :class:`Malformed` item: it is answered with an error and the connection
  goes on, as Klipper goes on after a request it cannot decode. Its ``id`` is the request's
  when it could be read (for a request too deep to decode, from its first bytes, where
  Moonraker writes it), else None.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

ETX = b"\x03"
MAX_REQUEST_BYTES = 1 << 20  # a gcode/script of a few thousand lines
MAX_INT_DIGITS = 19  # as an int64's; longer integers are refused, not converted
_LEADING_ID = re.compile(rb'\s*\{\s*"id"\s*:\s*(-?\d{1,18}|"[^"\\]{0,256}")\s*[,}]')


class FramingError(Exception):
    """The peer broke the framing: too large, not JSON, or not an object."""


@dataclass(frozen=True, slots=True)
class Request:
    """One request: ``id`` is echoed back (it may be absent: None)."""

    id: Any
    method: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Malformed:
    """A JSON object that is not a request this server can act on: answered with
    ``message`` as an error to ``id`` (None when it could not be read)."""

    id: Any
    message: str


Item = Request | Malformed


@dataclass(slots=True)
class Framer:
    """Bytes in, requests out; never holds more than ``limit_bytes`` of an unfinished one."""

    limit_bytes: int = MAX_REQUEST_BYTES
    _buffer: bytearray = field(default_factory=bytearray)
    _searched: int = 0  # bytes at the start of the buffer known to hold no end mark

    def push(self, data: bytes) -> None:
        """Take bytes as they arrived; raises :class:`FramingError` when the request being
        received grows past the bound."""
        self._buffer += data
        if self._buffer.find(ETX, self._searched) < 0:
            self._none_until_end()

    def pop(self) -> Item | None:
        """The next whole request (blank ones skipped), or None until more bytes come."""
        while (end := self._buffer.find(ETX, self._searched)) >= 0:
            chunk = bytes(self._buffer[:end])
            del self._buffer[: end + 1]  # from the front: O(1) for a bytearray
            self._searched = 0
            if chunk.strip():
                return parse_request(chunk)
        self._none_until_end()
        return None

    def _none_until_end(self) -> None:
        """No end mark in the buffer: remember it, and refuse an unfinished request that
        has grown past the bound."""
        self._searched = len(self._buffer)
        if self._searched > self.limit_bytes:
            raise FramingError(f"a request larger than {self.limit_bytes} bytes")

    def feed(self, data: bytes) -> list[Item]:
        """:meth:`push`, then every whole request (for tests and small inputs)."""
        self.push(data)
        items: list[Item] = []
        while (item := self.pop()) is not None:
            items.append(item)
        return items


class _Numbers:
    """The decoder's number hooks for one request: a number JSON cannot carry back (not
    finite, or an integer longer than :data:`MAX_INT_DIGITS`) is noted and read as None."""

    def __init__(self) -> None:
        self.refused: str | None = None

    def constant(self, text: str) -> None:
        self.refused = text

    def real(self, text: str) -> float | None:
        value = float(text)
        if math.isfinite(value):
            return value
        self.refused = text[:32]
        return None

    def integer(self, text: str) -> int | None:
        if len(text.lstrip("-")) <= MAX_INT_DIGITS:
            return int(text)
        self.refused = text[:32] + "..."
        return None


def parse_request(chunk: bytes) -> Item:
    """One request from the bytes between two end marks."""
    if len(chunk) > MAX_REQUEST_BYTES:
        raise FramingError(f"a request larger than {MAX_REQUEST_BYTES} bytes")
    numbers = _Numbers()
    decoder = json.JSONDecoder(parse_float=numbers.real, parse_int=numbers.integer,
                               parse_constant=numbers.constant)
    try:
        data = decoder.decode(chunk.decode())
    except RecursionError:
        return Malformed(leading_id(chunk), "the request is nested too deeply")
    except (ValueError, UnicodeDecodeError) as exc:
        raise FramingError(f"not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise FramingError("a request is not a JSON object")
    return _request(data, numbers.refused)


def _request(data: dict[str, Any], refused_number: str | None) -> Item:
    request_id = data.get("id")
    if not isinstance(request_id, int | float | str | None):
        return Malformed(None, "'id' must be a number or a string")
    if refused_number is not None:
        return Malformed(request_id, f"numbers must be finite and integers at most "
                                     f"{MAX_INT_DIGITS} digits long, not {refused_number}")
    method, params = data.get("method"), data.get("params", {})
    if not isinstance(method, str) or not isinstance(params, dict):
        return Malformed(request_id, "a request needs a string 'method' and an object "
                                     "'params'")
    return Request(request_id, method, params)


def leading_id(chunk: bytes) -> Any:
    """The id of a request that is not decoded, if it comes first (as Moonraker writes
    it): a short integer or string; else None."""
    match = _LEADING_ID.match(chunk)
    return None if match is None else json.loads(match.group(1))


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
