"""The MCU's data dictionary: message ids and formats, enumerations and constants.

Built from the JSON the MCU serves through ``identify`` (zlib-compressed); encodes commands by
name and decodes response payloads. Nothing but ``identify``/``identify_response`` is assumed.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

from server.backends.klipper.codec import (
    IDENTIFY,
    IDENTIFY_RESPONSE,
    MessageFormat,
    Params,
    ProtocolError,
    decode_vlq,
    encode_vlq,
    expand_enumerations,
)
from server.backends.klipper.stepcore import message


class Dictionary:
    """Encodes and decodes messages with the formats of one MCU build."""

    def __init__(self, data: Mapping[str, Any], *, lenient: bool = False) -> None:
        self.data = data
        self.lenient = lenient  # unknown messages end a payload instead of failing it
        self.version = str(data.get("version", ""))
        self.constants: dict[str, Any] = dict(data.get("config", {}))
        self.enumerations = expand_enumerations(data.get("enumerations", {}))
        self._reverse = {name: {v: k for k, v in table.items()}
                         for name, table in self.enumerations.items()}
        self.by_name: dict[str, MessageFormat] = {}
        self.by_id: dict[int, MessageFormat] = {}
        for section in ("commands", "responses", "output"):
            for text, msgid in data.get(section, {}).items():
                self._add(MessageFormat.parse(int(msgid), text, self.enumerations))
        self.pwm_max = int(self.constants.get("PWM_MAX", 255))  # a PWM output's full on
        self._prepared: dict[str, Callable[..., bytes]] = {}

    @classmethod
    def bootstrap(cls) -> Dictionary:
        """The two messages every MCU knows before its dictionary is read (anything else it
        says before then, such as the ``starting`` of a board that just booted, is skipped)."""
        return cls({"commands": {IDENTIFY: 1}, "responses": {IDENTIFY_RESPONSE: 0}},
                   lenient=True)

    @classmethod
    def from_compressed(cls, blob: bytes) -> Dictionary:
        try:
            return cls(json.loads(zlib.decompress(blob)))
        except (zlib.error, ValueError) as exc:
            raise ProtocolError(f"unreadable data dictionary: {exc}") from exc

    def _add(self, fmt: MessageFormat) -> None:
        self.by_name[fmt.name] = fmt
        self.by_id[fmt.msgid] = fmt

    def has(self, name: str) -> bool:
        return name in self.by_name

    def constant_int(self, name: str, default: int | None = None) -> int:
        value = self.constants.get(name, default)
        if value is None:
            raise ProtocolError(f"the MCU does not declare the constant {name}")
        return int(value)

    def enum_value(self, enum: str, name: str) -> int:
        """The number of an enumerated name (a pin), or ProtocolError naming the choices."""
        table = self.enumerations.get(enum, {})
        if name not in table:
            raise ProtocolError(f"unknown {enum} {name!r} on this MCU")
        return table[name]

    def encode(self, name: str, **params: Any) -> bytes:
        """One command message: id then parameters in declared order (enum names allowed)."""
        fmt = self.by_name.get(name)
        if fmt is None:
            raise ProtocolError(f"the MCU has no command {name!r}")
        out = bytearray()
        encode_vlq(out, fmt.msgid)
        for pname, kind, enum in fmt.params:
            if pname not in params:
                raise ProtocolError(f"{name}: missing parameter {pname}")
            value = params[pname]
            if kind == "s":
                data = bytes(value)
                encode_vlq(out, len(data))
                out += data
                continue
            if enum is not None and isinstance(value, str):
                value = self.enum_value(enum, value)
            encode_vlq(out, int(value))
        return bytes(out)

    def encoder(self, name: str) -> Callable[..., bytes]:
        """A prepared :meth:`encode` for a hot command: its id and field order resolved once,
        the VLQs compiled (``_stepcore.message``); called with the (integer, enum values as
        numbers) parameters in declared order (TypeError for another count). Gives the same
        bytes as :meth:`encode`."""
        prepared = self._prepared.get(name)
        if prepared is None:
            prepared = self._prepared[name] = self._prepare(name)
        return prepared

    def step_prefixes(self) -> tuple[bytes, bytes, bytes]:
        """The id VLQs of ``queue_step``, ``set_next_step_dir`` and ``reset_step_clock``, whose
        messages the compiled step axis (``_stepaxis.c``) encodes itself, once their
        parameters are checked to be the ones it sends, in that order."""
        expected = {"queue_step": [("oid", "u"), ("interval", "u"), ("count", "u"),
                                   ("add", "i")],
                    "set_next_step_dir": [("oid", "u"), ("dir", "u")],
                    "reset_step_clock": [("oid", "u"), ("clock", "u")]}
        prefixes = []
        for name, params in expected.items():
            fmt = self.by_name.get(name)
            if fmt is None:
                raise ProtocolError(f"the MCU has no command {name!r}")
            if [(p, k) for p, k, _ in fmt.params] != params:
                raise ProtocolError(f"{name} has unexpected parameters: {fmt.text!r}")
            prefixes.append(vlq(fmt.msgid))
        return prefixes[0], prefixes[1], prefixes[2]

    def _prepare(self, name: str) -> Callable[..., bytes]:
        fmt = self.by_name.get(name)
        if fmt is None:
            raise ProtocolError(f"the MCU has no command {name!r}")
        if any(kind == "s" for _, kind, _ in fmt.params):
            raise ProtocolError(f"{name}: a prepared encoder takes numbers only")
        return partial(message, vlq(fmt.msgid), len(fmt.params))  # compiled: VLQs by size

    def decode(self, payload: bytes) -> list[tuple[str, Params]]:
        """Every message in a block payload, as ``(name, params)`` (enum values as names)."""
        messages: list[tuple[str, Params]] = []
        pos = 0
        while pos < len(payload):
            msgid, pos = decode_vlq(payload, pos)
            fmt = self.by_id.get(msgid)
            if fmt is None:
                if self.lenient:
                    break
                raise ProtocolError(f"unknown message id {msgid}")
            params, pos = self._decode_params(fmt, payload, pos)
            messages.append((fmt.name, params))
        return messages

    def _decode_params(self, fmt: MessageFormat, payload: bytes, pos: int) -> tuple[Params, int]:
        params: Params = {}
        for pname, kind, enum in fmt.params:
            if kind == "s":
                length, pos = decode_vlq(payload, pos, signed=False)
                if pos + length > len(payload):
                    raise ProtocolError(f"{fmt.name}: string cut short")
                params[pname] = payload[pos:pos + length]
                pos += length
                continue
            value, pos = decode_vlq(payload, pos, signed=kind == "i")
            params[pname] = self._reverse[enum].get(value, value) if enum else value
        return params, pos


def vlq(value: int) -> bytes:
    """``value`` (-2**31 .. 2**32-1) as a VLQ (as :func:`~.codec.encode_vlq`), by size
    (compiled, as a prepared encoder's)."""
    return message(b"", 1, value)
