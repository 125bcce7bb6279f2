"""Bytes to lines and realtime commands: the byte-level half of the line protocol.

:class:`ByteScanner` splits a connection's byte stream into realtime commands and complete
lines; what a complete line means (RepRap framing, numbering, the dialect) and the replies are
:class:`server.protocol.lines.LineProtocol`, its subclass. No sockets, no asyncio, no clock.

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
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from typing import Self

from server.errors import CommandError, Error
from server.protocol.events import Dialect, Event, LineRejected, Realtime, RealtimeReceived

_ALWAYS_REALTIME = bytes(value for value in Realtime if value not in b"?!~")
_SPECIAL_GRBL = re.compile(rb"[\r\n?!~\x18\x80-\xff]")
_SPECIAL_REPRAP = re.compile(rb"[\r\n\x18\x80-\xff]")
_RUN_GRBL = re.compile(rb"[?!~\x18\x80-\xff]+")  # bytes taken one by one, line ends aside
_RUN_REPRAP = re.compile(rb"[\x18\x80-\xff]+")
_PLAIN_GRBL = bytes(b for b in range(0x80) if b not in b"?!~\x18")  # to delete: the rest is
_PLAIN_REPRAP = bytes(b for b in range(0x80) if b != 0x18)  # what the runs above would find
_STATUS_RUN = re.compile(rb"\?+")
_TEXT_REALTIME = re.compile("([" + "".join(chr(v) for v in Realtime if v >= 0x80) + "])")


class ByteScanner:
    """The byte scanning state of one connection; :meth:`_line_event` reads each line.

    Args:
        line_limit: longest accepted line in bytes, line ending excluded.
        websocket: every ``receive_data`` call is a whole message: its end also ends a line.
        dialect: GRBL takes ``?`` ``!`` ``~`` out as realtime commands; REPRAP leaves them text.
    """

    def __init__(self, line_limit: int, websocket: bool, dialect: Dialect) -> None:
        self.dialect = dialect
        self._line_limit = line_limit
        self._websocket = websocket
        self._buffer = bytearray()
        self._overflow = False
        self._skip_lf = False
        self._utf8_needed = 0
        self._c2_held = False

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

    def receive_ahead(self, data: bytes, *, final: bool = True,
                      keep: Callable[[bytes], bool] | None = None) -> list[Event]:
        """:meth:`receive_data` for bytes read ahead of the protocol that will execute them
        (the session's backlog twin): the same state afterwards and the same realtime events,
        but of the lines completed only those that may matter ahead of time are built and
        returned: those of which ``keep(bytes holding them)`` says so (the bytes may hold
        other lines too, with their line ends), and those that change how later bytes read
        (:meth:`_may_skim`). The rest cost a few passes in C per read, not Python work per
        line (2 MB of plain G-code: 0.65-1 s of loop time line by line, about 10 ms skimmed)."""
        events: list[Event] = []
        position = 0
        while position < len(data):
            grbl = self.dialect is Dialect.GRBL
            if position == 0 and not data.translate(None, _PLAIN_GRBL if grbl else _PLAIN_REPRAP):
                special = None  # the usual case, found without a search: no realtime byte
            else:
                special = (_RUN_GRBL if grbl else _RUN_REPRAP).search(data, position)
            end = len(data) if special is None else special.start()
            if end > position:
                self._take_plain(data[position:end], events, keep)
            if special is None:
                break
            self._feed(special.group(), events)  # exactly as receive_data, run by run
            position = special.end()
        if self._websocket and final:
            self._end_message(events)
        return events

    def _take_plain(self, text: bytes, events: list[Event],
                    keep: Callable[[bytes], bool] | None) -> None:
        """Bytes that hold no realtime byte (text and line ends): the lines they complete
        are skipped, unless ``keep`` or :meth:`_may_skim` asks to see them."""
        last_end = max(text.rfind(b"\n"), text.rfind(b"\r"))
        if last_end < 0:
            self._take_text(text)
            return
        self._end_utf8_character()
        lines = bytes(self._buffer) + text[: last_end + 1]
        if not self._may_skim(lines) or (keep is not None and keep(lines)):
            self._feed(text, events)
            return
        self.reset()  # every line but the last partial one has ended
        self._skip_lf = text[last_end] == 0x0D  # a LF may follow in the next bytes
        if last_end + 1 < len(text):
            self._append(text[last_end + 1 :])

    def _may_skim(self, lines: bytes) -> bool:
        """Whether complete ``lines`` (no realtime byte in them) may go unread: they change
        nothing in how later bytes are read (subclasses add line-level state)."""
        return True

    def copy(self) -> Self:
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

    # -- byte scanning -----------------------------------------------------------------------

    def _feed(self, data: bytes, events: list[Event]) -> None:
        if b"\n" in data and self._take_lines(data, events):
            return
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

    def _take_lines(self, data: bytes, events: list[Event]) -> bool:
        """The usual read, whole lines of plain text (no realtime or non-ASCII byte, lines
        ended by ``\n`` or ``\r\n``), split in C: the same events and state as byte by
        byte, without Python work per byte run. False (nothing taken) for any other read."""
        if data.translate(None, _PLAIN_GRBL if self.dialect is Dialect.GRBL else _PLAIN_REPRAP):
            return False
        skip = self._skip_lf and data[:1] == b"\n"  # the LF of a CR LF whose CR ended the
        if b"\r" in data:                             # last read (a CR LF here is a line)
            if data.count(b"\r") != data.count(b"\r\n"):
                return False  # a CR alone ends a line too: byte by byte
            data = data.replace(b"\r\n", b"\n")
        self._end_utf8_character()
        *lines, rest = data.split(b"\n")
        if skip:
            del lines[0]
        limit = self._line_limit
        for index, line in enumerate(lines):
            if index == 0 and (self._buffer or self._overflow):
                self._append(line)
                self._complete_line(events)
            elif len(line) > limit:
                message = f"line longer than {limit} bytes"
                events.append(LineRejected(CommandError(Error.LINE_OVERFLOW, message)))
            else:
                events.append(self._line_event(line))
        self._skip_lf = False
        if rest:
            self._append(rest)
        return True

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

    def _line_event(self, raw: bytes) -> Event:
        """The event for one complete line (``raw``: its bytes, without the line ending)."""
        raise NotImplementedError
