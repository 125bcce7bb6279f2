"""Klipper's wire format, sans I/O: message blocks, VLQ integers and the data dictionary.

A message block is ``<length><0x10|seq><payload><crc16 hi><crc16 lo><0x7e>`` (5 to 64 bytes);
the payload is a run of messages, each a VLQ message id followed by its VLQ parameters (strings
are a VLQ length and raw bytes). Message ids, parameter formats, enumerations (pin names) and
constants (``CLOCK_FREQ``, ``MCU``...) come from the MCU's zlib-compressed JSON data dictionary;
only ``identify`` (id 1) and ``identify_response`` (id 0) are fixed. See Klipper's
docs/Protocol.md.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from server.backends.klipper.stepcore import crc16
from server.backends.klipper.stepcore import frame as frame_block

MESSAGE_MIN = 5
MESSAGE_MAX = 64
PAYLOAD_MAX = MESSAGE_MAX - MESSAGE_MIN
SYNC = 0x7E
DEST = 0x10
SEQ_MASK = 0x0F

IDENTIFY = "identify offset=%u count=%c"
IDENTIFY_RESPONSE = "identify_response offset=%u data=%.*s"

Params = dict[str, Any]


class ProtocolError(Exception):
    """Bytes or a dictionary that do not follow the protocol."""


def crc16_ccitt(data: bytes) -> int:
    """The block checksum: CRC-16/MCRF4XX (CCITT polynomial, reflected, initial 0xFFFF),
    compiled (every block in and out is checked: a flooding board)."""
    return crc16(data)


def vlq_size(value: int) -> int:
    """Bytes the VLQ encoding of ``value`` takes (1 to 5)."""
    for size in range(1, 5):
        scale = 1 << (7 * size - 2)
        if -scale <= value < 3 * scale:
            return size
    return 5


def encode_vlq(out: bytearray, value: int) -> None:
    """Append ``value`` (-2**31 .. 2**32-1) as a VLQ: 7 bits a byte, most significant first."""
    for shift in range(7 * (vlq_size(value) - 1), 0, -7):
        out.append(((value >> shift) & 0x7F) | 0x80)
    out.append(value & 0x7F)


def decode_vlq(data: bytes, pos: int, signed: bool = True) -> tuple[int, int]:
    """The VLQ at ``data[pos]`` and the position after it."""
    try:
        byte = data[pos]
        value = byte & 0x7F
        if byte & 0x60 == 0x60:
            value -= 0x80
        while byte & 0x80:
            pos += 1
            byte = data[pos]
            value = (value << 7) | (byte & 0x7F)
    except IndexError as exc:
        raise ProtocolError("message cut short") from exc
    value &= 0xFFFFFFFF
    if signed and value & 0x80000000:
        value -= 1 << 32
    return value, pos + 1


def frame(seq: int, payload: bytes) -> bytes:
    """One message block with sequence number ``seq`` (mod 16) around ``payload``."""
    if len(payload) > PAYLOAD_MAX:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds {PAYLOAD_MAX}")
    return frame_block(DEST | (seq & SEQ_MASK), payload)  # compiled: length, crc, sync


@dataclass(frozen=True, slots=True)
class Block:
    """A received message block: its sequence number (4 bits) and payload."""

    seq: int
    payload: bytes


@dataclass(slots=True)
class BlockReader:
    """Splits a byte stream into valid blocks, skipping to the next sync byte after garbage."""

    buffer: bytearray = field(default_factory=bytearray)
    bad_blocks: int = 0

    def feed(self, data: bytes) -> list[Block]:
        buffer = self.buffer
        buffer += data
        blocks: list[Block] = []
        while buffer:
            if buffer[0] == SYNC:
                del buffer[0]
                continue
            length = buffer[0]
            if length < MESSAGE_MIN or length > MESSAGE_MAX:
                self._resync()
                continue
            if len(buffer) < length:
                break
            raw = bytes(buffer[:length])
            crc = crc16(raw[:-3])
            if raw[1] & ~SEQ_MASK != DEST or raw[-1] != SYNC or raw[-3:-1] != crc.to_bytes(2):
                self._resync()
                continue
            del buffer[:length]
            blocks.append(Block(raw[1] & SEQ_MASK, raw[2:-3]))
        return blocks

    def _resync(self) -> None:
        self.bad_blocks += 1
        index = self.buffer.find(SYNC)
        del self.buffer[: len(self.buffer) if index < 0 else index + 1]


_KINDS = {"%u": "u", "%i": "i", "%hu": "u", "%hi": "i", "%c": "u",
          "%s": "s", "%.*s": "s", "%*s": "s"}
_PARAM = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)=(%[a-z.*]+)$")


@dataclass(frozen=True, slots=True)
class MessageFormat:
    """One command or response: its id, name and parameters ``(name, kind, enumeration)``;
    kind is ``u`` (unsigned), ``i`` (signed) or ``s`` (bytes)."""

    msgid: int
    text: str
    name: str
    params: tuple[tuple[str, str, str | None], ...]

    @classmethod
    def parse(cls, msgid: int, text: str, enums: Mapping[str, Mapping[str, int]]) -> MessageFormat:
        name, *parts = text.split()
        params = []
        for part in parts:
            match = _PARAM.match(part)
            if match is None or match.group(2) not in _KINDS:
                raise ProtocolError(f"unknown parameter format {part!r} in {text!r}")
            pname = match.group(1)
            enum = next((e for e in enums if pname == e or pname.endswith("_" + e)), None)
            params.append((pname, _KINDS[match.group(2)], enum))
        return cls(msgid, text, name, tuple(params))


def expand_enumerations(raw: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, int]]:
    """Dictionary enumerations with ranges (``"PA0": [0, 16]``) spelled out one name each."""
    out: dict[str, dict[str, int]] = {}
    for enum_name, values in raw.items():
        table = out.setdefault(enum_name, {})
        for key, value in values.items():
            if isinstance(value, int):
                table[str(key)] = value
                continue
            root = str(key).rstrip("0123456789")
            first = int(str(key)[len(root):] or 0)
            start, count = value
            for index in range(count):
                table[f"{root}{first + index}"] = start + index
    return out
