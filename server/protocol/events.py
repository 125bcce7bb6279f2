"""What the line protocol emits: realtime commands, lines to execute and refused lines.

The vocabulary shared by the protocol (:class:`server.protocol.lines.LineProtocol`), the
session that acts on its events and everything that names a realtime command
(:class:`Realtime`). Plain data: no state, no I/O.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass
from typing import TypeAlias

from server.errors import CommandError

M110 = re.compile(r"\s*[Mm]0*110(?![\d.])")  # sets the line number, framed or not


class Realtime(enum.IntEnum):
    """Grbl 1.1 realtime command bytes."""

    STATUS = 0x3F
    HOLD = 0x21
    RESUME = 0x7E
    RESET = 0x18
    DOOR = 0x84
    JOG_CANCEL = 0x85
    FEED_100 = 0x90
    FEED_PLUS_10 = 0x91
    FEED_MINUS_10 = 0x92
    FEED_PLUS_1 = 0x93
    FEED_MINUS_1 = 0x94
    RAPID_100 = 0x95
    RAPID_50 = 0x96
    RAPID_25 = 0x97
    SPINDLE_100 = 0x99
    SPINDLE_PLUS_10 = 0x9A
    SPINDLE_MINUS_10 = 0x9B
    SPINDLE_PLUS_1 = 0x9C
    SPINDLE_MINUS_1 = 0x9D
    SPINDLE_STOP = 0x9E
    FLOOD = 0xA0
    MIST = 0xA1


class Dialect(enum.Enum):
    """How replies are worded: Grbl 1.1, or Marlin-style for RepRap hosts."""

    GRBL = "grbl"
    REPRAP = "reprap"


@dataclass(frozen=True, slots=True)
class FramedLine:
    """The RepRap framing of a line: its ``N`` number and the line without ``N..`` and ``*..``."""

    line_number: int
    text_without_framing: str

    @property
    def m110(self) -> bool:
        """The line is ``M110``, already acted on (same as ``LineReceived.handled``)."""
        return M110.match(self.text_without_framing) is not None


@dataclass(slots=True)
class LineReceived:
    """A complete line to execute (framing stripped; may be empty or only a comment).

    ``handled`` means the protocol already acted on the line (``M110``): answer ``ok`` only.
    Never changed once made (not declared frozen: a frozen dataclass is made with a Python
    call per field, and one is made per line).
    """

    text: str
    framed: FramedLine | None = None
    handled: bool = False


@dataclass(frozen=True, slots=True)
class RealtimeReceived:
    """A realtime command byte; it gets no reply."""

    command: Realtime


@dataclass(frozen=True, slots=True)
class LineRejected:
    """A line refused without executing; answer ``reply_error(error)`` in its turn.

    ``text``: what the line said, where it could be read (a frame refused for its checksum or
    number: an M112 in it still acts at once)."""

    error: CommandError
    text: str = ""


Event: TypeAlias = LineReceived | RealtimeReceived | LineRejected


class ResendError(CommandError):
    """A framed line that must be sent again (code 41 checksum, 42 line number).

    ``last_line`` is the last line number accepted when the line was refused; the sender is
    asked to resend from ``last_line + 1``.
    """

    def __init__(self, code: int, message: str, last_line: int) -> None:
        super().__init__(code, message)
        self.last_line = last_line

