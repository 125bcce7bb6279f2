"""Decoding one JSON-RPC 2.0 request frame, refusing what could hurt the server.

``decode_request`` turns a text frame into a request object or raises :class:`BadRequest` with
the error to answer. It refuses, without ever recursing deeply: nesting deeper than
:data:`MAX_DEPTH` (counted on the text before parsing, brackets inside strings excluded),
``NaN`` and ``Infinity`` (which Python's ``json`` accepts but JSON does not), numbers too large
for a float, and ids that are not a string, a finite number or null.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np

PARSE_ERROR, INVALID_REQUEST, METHOD_NOT_FOUND, INVALID_PARAMS, INTERNAL = (
    -32700,
    -32600,
    -32601,
    -32602,
    -32603,
)
MAX_DEPTH = 32
# A string, or an unterminated one up to the end of the text; possessive, so it never
# backtracks and every '"' starts a match: one linear pass, whatever the input.
_STRING = re.compile(r'"[^"\\]*+(?:\\.[^"\\]*+)*+(?:"|\\?\Z)', re.S)
_OPEN, _CLOSE = (ord("["), ord("{")), (ord("]"), ord("}"))


class BadRequest(Exception):
    """A frame refused before any method runs; answer ``code``/``message`` to ``request_id``."""

    def __init__(self, code: int, message: str, request_id: Any = None) -> None:
        super().__init__(message)
        self.code, self.message, self.request_id = code, message, request_id


def decode_request(text: str) -> dict[str, Any]:
    """One request or notification from a text frame (see the module docstring)."""
    if nesting_depth(text) > MAX_DEPTH:
        raise BadRequest(INVALID_REQUEST, f"nested deeper than {MAX_DEPTH} levels")
    try:
        message = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)
    except RecursionError as exc:  # not reached after the depth check; kept as a backstop
        raise BadRequest(INVALID_REQUEST, "nested too deeply") from exc
    except ValueError as exc:
        raise BadRequest(PARSE_ERROR, f"parse error: {exc}") from exc
    if (
        not isinstance(message, dict)
        or message.get("jsonrpc") != "2.0"
        or not isinstance(message.get("method"), str)
    ):
        request_id = message.get("id") if isinstance(message, dict) else None
        raise BadRequest(
            INVALID_REQUEST,
            "not a JSON-RPC 2.0 request (batches are not supported)",
            request_id if valid_id(request_id) else None,
        )
    if "id" in message and not valid_id(message["id"]):
        raise BadRequest(INVALID_REQUEST, "id must be a string, a finite number or null")
    return message


def valid_id(request_id: Any) -> bool:
    """A JSON-RPC id: a string, a finite number (not a boolean) or null."""
    if request_id is None or isinstance(request_id, str):
        return True
    if isinstance(request_id, bool):
        return False
    if isinstance(request_id, int):
        return True
    return isinstance(request_id, float) and math.isfinite(request_id)


def nesting_depth(text: str) -> int:
    """How deeply arrays and objects nest in a JSON text (an upper bound for invalid JSON);
    linear time, in C: strings are cut out by one regex, the brackets summed by numpy."""
    opening = text.count("[") + text.count("{")
    if opening <= MAX_DEPTH:
        return opening
    skeleton = np.frombuffer(_STRING.sub("", text).encode("utf-8", "surrogatepass"), np.uint8)
    opens = (skeleton == _OPEN[0]) | (skeleton == _OPEN[1])
    closes = (skeleton == _CLOSE[0]) | (skeleton == _CLOSE[1])
    steps = opens.view(np.int8) - closes.view(np.int8)
    return int(np.cumsum(steps, dtype=np.int32).max(initial=0))


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number out of range: {text[:40]}")
    return value
