"""Sans-I/O Grbl 1.1 / RepRap line protocol: one :class:`LineProtocol` per connection.

Bytes go in (``receive_data``; ``receive_text`` for WebSocket text frames), events come out in
stream order: :class:`RealtimeReceived`, :class:`LineReceived` (a line to execute) or
:class:`LineRejected` (answer ``reply_error`` without executing). ``reply_ok``, ``reply_error``,
``banner`` and ``push`` build the bytes to send. No sockets, no asyncio, no clock.

Input rules:

* ``\\n``, ``\\r`` and ``\\r\\n`` end one line, also with ``\\r\\n`` split between chunks.
  Every line, empty ones included, yields exactly one LineReceived or LineRejected.
* Realtime bytes are taken out wherever they appear and never count toward the line length:
  ``0x18`` and ``0x84``..``0xA1`` always, ``?`` ``!`` ``~`` in the GRBL dialect only (for a
  RepRap host they are text: ``M117 Done!`` must neither hold the machine nor break the
  checksum). ``C2 91`` (UTF-8 encoded) counts as ``0x91``. A byte ``0x80``..``0xBF`` that
  continues no UTF-8 character and is no known command is dropped, like Grbl does; a line that
  is not valid UTF-8 or holds control characters (tab aside) is rejected with ``error:1``.
* A line longer than ``line_limit`` bytes is dropped whole (``error:11``); at most
  ``line_limit`` bytes are buffered. Ctrl-X drops the partial line at its place in the stream.

RepRap framing ``N123 G1 X5*101`` (XOR of the bytes before the last ``*``) is checked here in
both dialects: a bad checksum is :class:`ResendError` 41, a line number other than last + 1 is
42 (the first framed line starts the sequence). ``M110`` (framed or not) sets the last line
number (``M110 N<k>``, else the frame's ``N``) and comes out with ``handled=True``: answer ``ok``.

Dialect ``"auto"``: GRBL until the first non-empty line is framed or is ``M105``/``M110``/
``M115`` (what printrun and OctoPrint send first), then REPRAP for good. REPRAP replies follow
Marlin (banner ``start``, ``ok T:..``, ``Error:``/``Resend:``/``echo:`` wording; see
:func:`server.protocol.reports.format_reprap_error`), never ``error:N``, on which OctoPrint
disconnects.
"""

from __future__ import annotations

import copy
import enum
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce
from operator import xor
from typing import TypeAlias

from server.errors import CommandError, Error
from server.protocol.reports import GRBL_VERSION, format_reprap_error

GRBL_BANNER = f"Grbl {GRBL_VERSION} ['$' for help]"


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
        return _M110.match(self.text_without_framing) is not None


@dataclass(frozen=True, slots=True)
class LineReceived:
    """A complete line to execute (framing stripped; may be empty or only a comment).

    ``handled`` means the protocol already acted on the line (``M110``): answer ``ok`` only.
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
    """A line refused without executing; answer ``reply_error(error)`` in its turn."""

    error: CommandError


Event: TypeAlias = LineReceived | RealtimeReceived | LineRejected


class ResendError(CommandError):
    """A framed line that must be sent again (code 41 checksum, 42 line number).

    ``last_line`` is the last line number accepted when the line was refused; the sender is
    asked to resend from ``last_line + 1``.
    """

    def __init__(self, code: int, message: str, last_line: int) -> None:
        super().__init__(code, message)
        self.last_line = last_line


_ALWAYS_REALTIME = bytes(value for value in Realtime if value not in b"?!~")
_SPECIAL_GRBL = re.compile(rb"[\r\n?!~\x18\x80-\xff]")
_SPECIAL_REPRAP = re.compile(rb"[\r\n\x18\x80-\xff]")
_STATUS_RUN = re.compile(rb"\?+")
_TEXT_REALTIME = re.compile("([" + "".join(chr(v) for v in Realtime if v >= 0x80) + "])")
_LINE_BREAK = re.compile("[\n\r\v\f\x1c-\x1e\x85\u2028\u2029]")  # what str.splitlines splits on
_CONTROL = re.compile(r"[\x00-\x08\x0a-\x1f\x7f-\x9f]")
_N_WORD = re.compile(r"[Nn]\s*(-?\d+)")
_CHECKSUM_FIELD = re.compile(r"\s*(\d+)\s*")
_M110 = re.compile(r"\s*[Mm]0*110(?![\d.])")
_REPRAP_GREETING = re.compile(r"[Mm]0*(?:105|110|115)(?![\d.])")
_COMMENT = re.compile(r"\([^)]*\)|;.*")
_MSG_FIELD = re.compile(r"\[MSG:[^\]]*\]")
_REPLY_ONLY = ("[VER:", "[OPT:", "[HLP:")


class LineProtocol:
    """The line protocol of one connection. See the module docstring for the rules.

    Args:
        line_limit: longest accepted line in bytes, line ending excluded.
        dialect: ``"auto"`` (GRBL until a RepRap host is recognised), ``"grbl"`` or ``"reprap"``.
        websocket: every ``receive_data`` call is a whole message: its end also ends a line.
    """

    def __init__(
        self, *, line_limit: int = 256, dialect: str = "auto", websocket: bool = False
    ) -> None:
        if dialect not in ("auto", "grbl", "reprap"):
            raise ValueError(f"unknown dialect {dialect!r}: expected auto, grbl or reprap")
        self.dialect = Dialect.REPRAP if dialect == "reprap" else Dialect.GRBL
        self._detecting = dialect == "auto"
        self._line_limit = line_limit
        self._websocket = websocket
        self._buffer = bytearray()
        self._overflow = False
        self._skip_lf = False
        self._utf8_needed = 0
        self._c2_held = False
        self._last_line = 0
        self._sequence_known = False

    # -- input -------------------------------------------------------------------------------

    def receive_data(self, data: bytes, *, final: bool = True) -> list[Event]:
        """Feed received bytes; return the events they complete, in stream order.

        ``final=False`` (WebSocket only): more of the same message follows, so its end does
        not end a line yet; a transport feeds a large message in slices this way.
        """
        events: list[Event] = []
        self._feed(data, events)
        if self._websocket and final:
            self._end_message(events)
        return events

    def receive_text(self, text: str, *, final: bool = True) -> list[Event]:
        """Feed one WebSocket text frame: a whole message (a last line needs no newline), or
        with ``final=False`` a slice of one that more slices complete.

        A character whose code point is a realtime byte (``U+0091``...) is that realtime command.
        """
        events: list[Event] = []
        for index, piece in enumerate(_TEXT_REALTIME.split(text)):
            if index % 2:
                self._realtime(ord(piece), events)
            elif piece:
                self._feed(piece.encode("utf-8"), events)
        if final:
            self._end_message(events)
        return events

    def copy(self) -> LineProtocol:
        """An independent twin in the same state: it sees bytes ahead of this one exactly as
        this one will (the session uses it to find realtime bytes in held-back input)."""
        twin = copy.copy(self)
        twin._buffer = bytearray(self._buffer)
        return twin

    def reset(self) -> None:
        """Forget a partial line (after a reset). Keeps the dialect and the line numbering.

        Ctrl-X received on this connection already did this at its place in the stream.
        """
        self._buffer.clear()
        self._overflow = False
        self._utf8_needed = 0
        self._c2_held = False

    # -- output ------------------------------------------------------------------------------

    def banner(self) -> bytes:
        """The welcome text: ``\\r\\nGrbl 1.1h ['$' for help]\\r\\n``, or ``start`` for REPRAP."""
        if self.dialect is Dialect.REPRAP:
            return b"start\r\n"
        return f"\r\n{GRBL_BANNER}\r\n".encode()

    def reply_ok(self, messages: Sequence[str] = (), ok_suffix: str = "") -> bytes:
        """Message lines, then ``ok``.

        ``ok_suffix`` goes on the ``ok`` line in REPRAP (``ok T:0.0 /0.0``); in GRBL, whose
        senders expect a bare ``ok``, it becomes one more message line before it.
        """
        lines = [_checked_line(message) for message in messages]
        if ok_suffix and self.dialect is Dialect.GRBL:
            lines.append(_checked_line(ok_suffix))
            ok_suffix = ""
        lines.append(f"ok {ok_suffix}" if ok_suffix else "ok")
        return _encode(lines)

    def reply_error(self, error: CommandError) -> bytes:
        """The answer to a refused line: ``error:N`` (GRBL) or Marlin-style lines (REPRAP)."""
        if self.dialect is Dialect.GRBL:
            return f"error:{error.code}\r\n".encode()
        last = error.last_line if isinstance(error, ResendError) else self._last_line
        return _encode(format_reprap_error(error.code, error.message, last))

    def push(self, message: str) -> bytes:
        """An unsolicited line (status report, ``[MSG:...]``, ``ALARM:N``) with its line ending.

        Raises:
            ValueError: the message spans lines, would read as a reply (``ok`` outside
                ``[MSG:...]``), or is a reply-only report (``[VER:``, ``[OPT:``, ``[HLP:``).
        """
        _checked_line(message)
        if message.startswith(_REPLY_ONLY):
            raise ValueError(f"{message[:5]} is only sent as a reply, never pushed")
        if "ok" in _MSG_FIELD.sub("", message):
            raise ValueError(f"a pushed line must not contain 'ok' outside [MSG:]: {message!r}")
        return _encode([message])

    # -- byte scanning -----------------------------------------------------------------------

    def _feed(self, data: bytes, events: list[Event]) -> None:
        position = 0
        while position < len(data):
            special = self._special().search(data, position)
            end = len(data) if special is None else special.start()
            if end > position:
                self._take_text(data[position:end])
            if special is None:
                return
            if data[end] == 0x3F and self.dialect is Dialect.GRBL:  # a run of '?': one request
                self._end_utf8_character()
                self._realtime(0x3F, events)
                run = _STATUS_RUN.match(data, end)
                position = run.end() if run else end + 1
                continue
            self._take_special(data[end], events)
            position = end + 1

    def _special(self) -> re.Pattern[bytes]:
        return _SPECIAL_GRBL if self.dialect is Dialect.GRBL else _SPECIAL_REPRAP

    def _take_text(self, chunk: bytes) -> None:
        self._end_utf8_character()
        self._append(chunk)

    def _take_special(self, byte: int, events: list[Event]) -> None:
        if byte >= 0x80:
            self._take_high(byte, events)
            return
        self._end_utf8_character()
        if byte in b"\r\n":
            self._line_end(byte, events)
        else:
            self._realtime(byte, events)

    def _take_high(self, byte: int, events: list[Event]) -> None:
        is_continuation = byte <= 0xBF
        if self._c2_held:
            self._c2_held = False
            if byte in _ALWAYS_REALTIME:
                self._realtime(byte, events)
                return
            self._append(b"\xc2")
            if is_continuation:
                self._append(bytes((byte,)))
                return
        elif self._utf8_needed and is_continuation:
            self._utf8_needed -= 1
            self._append(bytes((byte,)))
            return
        self._take_fresh_high(byte, events)

    def _take_fresh_high(self, byte: int, events: list[Event]) -> None:
        """A byte >= 0x80 that does not continue a UTF-8 character."""
        self._utf8_needed = 0
        if byte <= 0xBF:
            if byte in _ALWAYS_REALTIME:
                self._realtime(byte, events)
            return  # unknown extended-ASCII command: dropped, as Grbl does
        if byte == 0xC2:
            self._c2_held = True  # U+0080..U+00BF, or a UTF-8 encoded realtime byte
            return
        self._append(bytes((byte,)))
        if 0xC3 <= byte <= 0xF4:
            self._utf8_needed = 1 if byte < 0xE0 else 2 if byte < 0xF0 else 3

    def _end_utf8_character(self) -> None:
        """An ASCII byte: an unfinished UTF-8 character stays unfinished (invalid)."""
        self._utf8_needed = 0
        if self._c2_held:
            self._c2_held = False
            self._append(b"\xc2")

    def _append(self, chunk: bytes) -> None:
        self._skip_lf = False
        if self._overflow:
            return
        if len(self._buffer) + len(chunk) > self._line_limit:
            self._overflow = True
            self._buffer.clear()
            return
        self._buffer += chunk

    def _realtime(self, byte: int, events: list[Event]) -> None:
        command = Realtime(byte)
        if command is Realtime.RESET:
            self.reset()
        events.append(RealtimeReceived(command))

    def _line_end(self, byte: int, events: list[Event]) -> None:
        if byte == 0x0A and self._skip_lf:
            self._skip_lf = False
            return
        self._complete_line(events)
        self._skip_lf = byte == 0x0D

    def _end_message(self, events: list[Event]) -> None:
        self._end_utf8_character()
        if self._buffer or self._overflow:
            self._complete_line(events)
        self._skip_lf = False

    def _complete_line(self, events: list[Event]) -> None:
        raw, overflow = bytes(self._buffer), self._overflow
        self.reset()
        if overflow:
            message = f"line longer than {self._line_limit} bytes"
            events.append(LineRejected(CommandError(Error.LINE_OVERFLOW, message)))
        else:
            events.append(self._line_event(raw))

    # -- lines -------------------------------------------------------------------------------

    def _line_event(self, raw: bytes) -> Event:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            return self._garbage(raw, "invalid UTF-8")
        if _CONTROL.search(text):
            return self._garbage(raw, "control character in line")
        frame = _split_frame(text)
        self._detect_dialect(text, framed=frame is not None)
        if frame is not None:
            return self._framed_event(*frame)
        if _M110.match(text):
            self._set_last_line(text, None)
            return LineReceived(text, None, handled=True)
        return LineReceived(text)

    def _garbage(self, raw: bytes, reason: str) -> LineRejected:
        stripped = raw.lstrip()
        if stripped[:1] in (b"N", b"n") and b"*" in stripped:
            return LineRejected(ResendError(Error.CHECKSUM, reason, self._last_line))
        return LineRejected(CommandError(Error.EXPECTED_COMMAND_LETTER, reason))

    def _detect_dialect(self, text: str, *, framed: bool) -> None:
        if not self._detecting:
            return
        content = _COMMENT.sub("", text).strip()
        if not content:
            return
        self._detecting = False
        if framed or _REPRAP_GREETING.match(content):
            self.dialect = Dialect.REPRAP

    def _framed_event(self, number_text: str, body: str, checksum_text: str, head: str) -> Event:
        field = _CHECKSUM_FIELD.fullmatch(checksum_text)
        if field is None:
            return self._resend(Error.CHECKSUM, f"bad checksum field '*{checksum_text}'")
        computed = reduce(xor, head.encode("utf-8"), 0)
        if int(field.group(1)) != computed:
            return self._resend(Error.CHECKSUM, f"checksum {field.group(1)} != computed {computed}")
        number = int(number_text)
        framed = FramedLine(number, body)
        if _M110.match(body):
            self._set_last_line(body, number)
            return LineReceived(body, framed, handled=True)
        if self._sequence_known and number != self._last_line + 1:
            expected = self._last_line + 1
            return self._resend(Error.LINE_NUMBER_SEQUENCE, f"got N{number}, expected N{expected}")
        self._last_line = number
        self._sequence_known = True
        return LineReceived(body, framed)

    def _resend(self, code: int, message: str) -> LineRejected:
        return LineRejected(ResendError(code, message, self._last_line))

    def _set_last_line(self, m110_text: str, frame_number: int | None) -> None:
        argument = _N_WORD.search(_COMMENT.sub("", m110_text))
        if argument is not None:
            self._last_line = int(argument.group(1))
        elif frame_number is not None:
            self._last_line = frame_number
        else:
            return
        self._sequence_known = True


def _split_frame(text: str) -> tuple[str, str, str, str] | None:
    """``(number, body, checksum field, checksummed head)`` of a framed line, else None."""
    head = text.lstrip()
    if head[:1] not in ("N", "n") or "*" not in head:
        return None
    head, _, checksum_text = head.rpartition("*")
    number = _N_WORD.match(head)
    if number is None:
        return None
    return number.group(1), head[number.end() :].strip(), checksum_text, head


def _checked_line(line: str) -> str:
    if _LINE_BREAK.search(line):
        raise ValueError(f"one line per message, got {line!r}")
    if line.startswith("ok"):
        raise ValueError(f"a message line must not read as 'ok': {line!r}")
    return line


def _encode(lines: Sequence[str]) -> bytes:
    return "".join(line + "\r\n" for line in lines).encode("utf-8")
