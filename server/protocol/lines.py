"""Sans-I/O Grbl 1.1 / RepRap line protocol: one :class:`LineProtocol` per connection.

Bytes go in (``receive_data``; ``receive_text`` for WebSocket text frames), events come out in
stream order: :class:`RealtimeReceived`, :class:`LineReceived` (a line to execute) or
:class:`LineRejected` (answer ``reply_error`` without executing). ``reply_ok``, ``reply_error``,
``banner`` and ``push`` build the bytes to send. No sockets, no asyncio, no clock.

The events are :mod:`server.protocol.events`; splitting bytes into realtime commands and lines
(line endings, realtime bytes, UTF-8, the line limit) is :mod:`server.protocol.scanner`, whose
:class:`~server.protocol.scanner.ByteScanner` this class extends with what a line means.

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

import re
from collections.abc import Sequence
from functools import reduce
from operator import xor

from server.errors import CommandError, Error, SoftLimitError
from server.protocol.events import (
    M110,
    Dialect,
    Event,
    FramedLine,
    LineReceived,
    LineRejected,
    ResendError,
)
from server.protocol.reports import GRBL_VERSION, format_reprap_error, format_reprap_notices
from server.protocol.scanner import ByteScanner

GRBL_BANNER = f"Grbl {GRBL_VERSION} ['$' for help]"
OK_PREFIX = "ok "  # a reply's last message that starts so is its ok line's suffix

_LINE_BREAK = re.compile("[\n\r\v\f\x1c-\x1e\x85\u2028\u2029]")  # what str.splitlines splits on
_CONTROL = re.compile(r"[\x00-\x08\x0a-\x1f\x7f-\x9f]")
_N_WORD = re.compile(r"[Nn]\s*(-?\d+)")
_CHECKSUM_FIELD = re.compile(r"\s*(\d+)\s*")
_REPRAP_GREETING = re.compile(r"[Mm]0*(?:105|110|115)(?![\d.])")
_COMMENT = re.compile(r"\([^)]*\)|;.*")
_MSG_FIELD = re.compile(r"\[MSG:[^\]]*\]")
_REPLY_ONLY = ("[VER:", "[OPT:", "[HLP:")
_NUMBERING = re.compile(rb"[Mm]0*110")  # in lines that may set the line number


class LineProtocol(ByteScanner):
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
        super().__init__(
            line_limit, websocket, Dialect.REPRAP if dialect == "reprap" else Dialect.GRBL
        )
        self._detecting = dialect == "auto"
        self._last_line = 0
        self._sequence_known = False

    # -- output ------------------------------------------------------------------------------

    def banner(self) -> bytes:
        """The welcome text: ``\\r\\nGrbl 1.1h ['$' for help]\\r\\n``, or ``start`` for REPRAP."""
        if self.dialect is Dialect.REPRAP:
            return b"start\r\n"
        return f"\r\n{GRBL_BANNER}\r\n".encode()

    def reply_ok(self, messages: Sequence[str] = (), ok_suffix: str = "") -> bytes:
        """Message lines, then ``ok``.

        ``ok_suffix`` goes on the ``ok`` line in REPRAP (``ok T:0.0 /0.0``); in GRBL, whose
        senders expect a bare ``ok``, it becomes one more message line before it. A handler
        asks for it with a last message ``ok <suffix>`` (M105's ``ok T:..``: Marlin answers
        on one line, and OctoPrint takes a ``T:`` line without ``ok`` for a heat-up).
        """
        if not messages and not ok_suffix:
            return _OK  # the reply to almost every line
        if messages and messages[-1].startswith(OK_PREFIX) and not ok_suffix:
            ok_suffix, messages = messages[-1][len(OK_PREFIX) :], messages[:-1]
        lines = [_checked_line(message) for message in messages]
        if ok_suffix and self.dialect is Dialect.GRBL:
            lines.append(_checked_line(ok_suffix))
            ok_suffix = ""
        lines.append(f"ok {ok_suffix}" if ok_suffix else "ok")
        return _encode(lines)

    def reply_error(self, error: CommandError) -> bytes:
        """The answer to a refused line: ``error:N`` (GRBL) or Marlin-style lines (REPRAP).
        A soft limit is answered, as by Grbl, by its ``ALARM:2`` alone (pushed to everyone):
        senders count that line as the reply (``b""`` here)."""
        if self.dialect is Dialect.GRBL:
            if isinstance(error, SoftLimitError):
                return b""
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
        if self.dialect is Dialect.REPRAP:
            return _encode([message, *format_reprap_notices(message)])
        return _encode([message])

    # -- lines -------------------------------------------------------------------------------

    def _line_event(self, raw: bytes) -> Event:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            return self._garbage(raw, "invalid UTF-8")
        if _CONTROL.search(text):
            return self._garbage(raw, "control character in line")
        frame = _split_frame(text) if "*" in text else None  # (a frame has a checksum)
        if self._detecting:
            self._detect_dialect(text, framed=frame is not None)
        if frame is not None:
            return self._framed_event(*frame)
        if "110" in text and M110.match(text):  # (the code's digits, looked for in C first)
            self._set_last_line(text, None)
            return LineReceived(text, None, handled=True)
        return LineReceived(text)

    def _garbage(self, raw: bytes, reason: str) -> LineRejected:
        stripped = raw.lstrip()
        if stripped[:1] in (b"N", b"n") and b"*" in stripped:
            return LineRejected(ResendError(Error.CHECKSUM, reason, self._last_line))
        return LineRejected(CommandError(Error.EXPECTED_COMMAND_LETTER, reason))

    def _may_skim(self, lines: bytes) -> bool:
        """Lines read ahead go unread only once the dialect is known, and when none of them
        may be framed or an ``M110`` (the line numbering later lines are checked against)."""
        if self._detecting or b"*" in lines:
            return False
        if b"110" not in lines or (b"M" not in lines and b"m" not in lines):
            return True  # (faster than the search below, which decides)
        return _NUMBERING.search(lines) is None

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
            return self._resend(Error.CHECKSUM, f"bad checksum field '*{checksum_text}'", body)
        computed = reduce(xor, head.encode("utf-8"), 0)
        if int(field.group(1)) != computed:
            return self._resend(
                Error.CHECKSUM, f"checksum {field.group(1)} != computed {computed}", body)
        number = int(number_text)
        framed = FramedLine(number, body)
        if M110.match(body):
            self._set_last_line(body, number)
            return LineReceived(body, framed, handled=True)
        if self._sequence_known and number != self._last_line + 1:
            expected = self._last_line + 1
            return self._resend(
                Error.LINE_NUMBER_SEQUENCE, f"got N{number}, expected N{expected}", body)
        self._last_line = number
        self._sequence_known = True
        return LineReceived(body, framed)

    def _resend(self, code: int, message: str, body: str) -> LineRejected:
        return LineRejected(ResendError(code, message, self._last_line), body)

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


_OK = b"ok\r\n"


def _encode(lines: Sequence[str]) -> bytes:
    return "".join(line + "\r\n" for line in lines).encode("utf-8")
