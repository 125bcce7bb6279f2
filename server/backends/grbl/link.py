"""The Grbl serial protocol as seen from the host: a pure, sans-I/O link core.

:class:`Link` keeps the character-counting send window of one controller connection and
matches the controller's answers to the lines sent, in order:

* :meth:`Link.send` admits a line only while the bytes of unanswered lines plus its own fit in
  the controller's receive buffer (Grbl's "character counting"; 127 bytes on an Arduino);
* :meth:`Link.receive` turns the controller's bytes into events: each ``ok`` / ``error:N``
  answers the oldest unanswered line (:class:`Answered`, with the lines the controller printed
  for it before, such as ``[PRB:...]`` or ``$$`` output), ``<...>`` is a :class:`StatusReport`,
  ``ALARM:N`` an :class:`AlarmReport`, the welcome line a :class:`Banner`; anything else while
  no line is waiting is :class:`Feedback` (``[MSG:...]`` after a reset);
* :meth:`Link.reset` (Ctrl-X sent) and :meth:`Link.lost` drop every unanswered line: after a
  reset the controller empties its buffer and never answers them, so answers are ignored and
  nothing is sent until its banner arrives again.

grblHAL (:meth:`Link.use_grblhal`, once its ``$I`` says ``[FIRMWARE:grblHAL]``) makes an error
sticky: after ``error:N`` it answers every later G-code line with the same error, unexecuted,
until an empty line. Each line is then sent ending ``\r\n``, which grblHAL takes as one line
end; after a G-code error its ``\n`` is that empty line, so the error clears at once and the
lines behind it run as on Grbl 1.1h. A ``$`` line's ``\n`` clears nothing (the rig shows it):
it is followed by an empty line of its own. The clearing line's ``ok`` answers nothing: it is
dropped.

Nothing here does I/O or knows asyncio; the transport (``controller.py``) writes the bytes.
Units: positions mm, feed mm/min as the controller reports it.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

from server.backends.grbl.reports import ControllerStatus, parse_status

DEFAULT_BUFFER_BYTES = 127  # Grbl's 128-byte serial buffer, one byte kept free
MAX_LINE_BYTES = 1024  # a controller line longer than this is junk (noise on the wire)
MAX_MESSAGES_PER_LINE = 256  # lines kept for one line in flight ($$ prints about 35)
MAX_MESSAGE_BYTES = 16384  # and their bytes; the rest is counted and dropped
_BANNER = re.compile(r"^Grbl(?:HAL)?\s+\S+.*\[.*\]", re.I)
_ANSWER = re.compile(r"^(?:ok|error:(\d+))$", re.I)
_ALARM = re.compile(r"^ALARM:(\d+)$", re.I)
_SETTING = re.compile(r"^\$(\d+)=([-+]?[0-9]*\.?[0-9]+)")
_OPTIONS = re.compile(r"^\[OPT:[^,\]]*,(\d{1,5}),(\d{1,5})\b")
_COMMENT = re.compile(r"\([^)]*\)|;.*")
_SPACE = re.compile(r"\s+")


@dataclass(frozen=True, slots=True)
class Answered:
    """The controller answered line ``token``: ``error`` is None for ``ok``."""

    token: int
    messages: tuple[str, ...]
    error: int | None


@dataclass(frozen=True, slots=True)
class StatusReport:
    status: ControllerStatus


@dataclass(frozen=True, slots=True)
class AlarmReport:
    code: int


@dataclass(frozen=True, slots=True)
class Banner:
    """The controller (re)started: ``dropped`` are the lines it will never answer."""

    text: str
    dropped: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class Feedback:
    """A line that answers nothing we sent (``[MSG:...]``, a stray ``ok``...)."""

    text: str


LinkEvent = Answered | StatusReport | AlarmReport | Banner | Feedback


@dataclass(slots=True)
class _InFlight:
    token: int
    size_bytes: int
    clears: bool = False  # grblHAL: an empty line follows it (a $ line), whose ok comes next
    messages: list[str] = field(default_factory=list)
    message_bytes: int = 0
    dropped: int = 0  # lines printed for it beyond the bounds

    def keep(self, text: str) -> bool:
        """Keep a line the controller printed before answering this one, within bounds."""
        if (len(self.messages) >= MAX_MESSAGES_PER_LINE
                or self.message_bytes + len(text) > MAX_MESSAGE_BYTES):
            self.dropped += 1
            return False
        self.messages.append(text)
        self.message_bytes += len(text)
        return True

    def answered(self) -> tuple[str, ...]:
        if self.dropped:
            return (*self.messages, f"[MSG:{self.dropped} more lines from the controller]")
        return tuple(self.messages)


class Link:
    """One controller connection's send window and reply matching; see the module docstring."""

    def __init__(self, buffer_bytes: int = DEFAULT_BUFFER_BYTES) -> None:
        self.buffer_bytes = buffer_bytes
        self.used_bytes = 0
        self.awaiting_banner = True
        self._in_flight: deque[_InFlight] = deque()
        self._next_token = 0
        self._partial = bytearray()
        self.garbled_reports = 0  # status reports that did not parse (dropped)
        self.dropped_lines = 0  # too long, or printed beyond the bounds of a line in flight
        self._discarding = False  # inside a line already too long: drop up to its end
        self._wco: tuple[float, ...] | None = None
        self.line_end = b"\n"
        self.sticky_errors = False  # grblHAL: an error sticks until an empty line
        self._clearing = 0  # errors whose clearing empty line's ok is still to come

    def use_grblhal(self) -> None:
        """The controller is grblHAL: lines end ``\r\n`` (see the module docstring)."""
        self.line_end = b"\r\n"
        self.sticky_errors = True

    @property
    def wco_mm(self) -> tuple[float, ...] | None:
        """The last work coordinate offset the board reported (``WCO:``, sent now and then)."""
        return self._wco

    # -- sending ----------------------------------------------------------------------------
    @property
    def in_flight(self) -> int:
        """Lines sent and not yet answered."""
        return len(self._in_flight)

    def fits(self, line_bytes: int) -> bool:
        """Whether a line of ``line_bytes`` (newline included) may be sent now. A line longer
        than the whole buffer goes alone (the controller reads it as its buffer drains)."""
        if self.awaiting_banner:
            return False
        if not self._in_flight:
            return True
        return self.used_bytes + line_bytes <= self.buffer_bytes

    def send(self, text: str) -> tuple[int, bytes]:
        """Admit one line: its token (for :class:`Answered`) and the bytes to write."""
        clears = self.sticky_errors and text.startswith("$")
        data = text.encode("ascii", "replace") + self.line_end * (2 if clears else 1)
        if not self.fits(len(data)):
            raise RuntimeError("the controller's buffer has no room for this line")
        token = self._next_token
        self._next_token += 1
        self._in_flight.append(_InFlight(token, len(data), clears))
        self.used_bytes += len(data)
        return token, data

    def reset(self) -> list[int]:
        """Ctrl-X was sent: the unanswered lines are gone; wait for the banner."""
        dropped = [line.token for line in self._in_flight]
        self._in_flight.clear()
        self.used_bytes = 0
        self._clearing = 0
        self.awaiting_banner = True
        return dropped

    def lost(self) -> list[int]:
        """The connection is gone: every unanswered line is dropped, input discarded."""
        self._partial.clear()
        self._wco = None
        self.line_end, self.sticky_errors = b"\n", False  # the next board says what it is
        return self.reset()

    # -- receiving --------------------------------------------------------------------------
    def receive(self, data: bytes) -> list[LinkEvent]:
        """Bytes from the controller, in order; complete lines become events. A chatty or
        noisy board sends thousands of lines a second: each costs a split and a look at its
        first character unless it can be a report, an answer, an alarm or the banner."""
        self._partial += data
        events: list[LinkEvent] = []
        if b"\n" in data:
            *lines, rest = self._partial.split(b"\n")
            self._partial = bytearray(rest)
            for raw in lines:
                discarding, self._discarding = self._discarding, False
                if len(raw) > MAX_LINE_BYTES:
                    self.dropped_lines += 1
                    continue
                text = raw.decode("ascii", "replace").strip()
                if text and not discarding:
                    event = self._line(text)
                    if event is not None:
                        events.append(event)
        if len(self._partial) > MAX_LINE_BYTES:
            self._partial.clear()
            self._discarding = True
            self.dropped_lines += 1
        return events

    def _line(self, text: str) -> LinkEvent | None:
        first = text[0]
        if first == "<" and text.endswith(">"):
            try:
                status = parse_status(text, self._wco)
            except ValueError:  # noise on the wire: the next report (a poll away) will do
                self.garbled_reports += 1
                return None
            if status.wco_mm is not None:
                self._wco = status.wco_mm
            return StatusReport(status)
        if first in "Gg" and _BANNER.match(text):
            dropped = tuple(self.reset())
            self.awaiting_banner = False
            return Banner(text, dropped)
        alarm = _ALARM.match(text) if first in "Aa" else None
        if alarm:
            return AlarmReport(int(alarm.group(1)))
        answer = _ANSWER.match(text) if first in "OoEe" else None
        if answer:
            return self._answer(text, None if answer.group(1) is None else int(answer.group(1)))
        if self._in_flight and not self.awaiting_banner:
            if not self._in_flight[0].keep(text):
                self.dropped_lines += 1
            return None
        return Feedback(text)

    def _answer(self, text: str, error: int | None) -> LinkEvent | None:
        if self._clearing and error is None and not self.awaiting_banner:
            self._clearing -= 1  # the ok of an errored line's own \n: grblHAL's clearing
            return None
        if self.awaiting_banner or not self._in_flight:
            return Feedback(text)  # an answer to a line dropped by a reset
        line = self._in_flight.popleft()
        if line.clears or (error is not None and self.sticky_errors):
            self._clearing += 1
        self.used_bytes -= line.size_bytes
        return Answered(line.token, line.answered(), error)


# -- line and report parsing ------------------------------------------------------------------
def compact(text: str) -> str:
    """A line as Grbl stores it: comments and white space removed (fewer bytes to count)."""
    return _SPACE.sub("", _COMMENT.sub("", text))


def parse_build_options(lines: tuple[str, ...] | list[str]) -> tuple[int, int] | None:
    """``$I``'s ``[OPT:V,15,128]``: (planner blocks, receive buffer bytes), or None."""
    for line in lines:
        match = _OPTIONS.match(line.strip())
        if match:
            return int(match.group(1)), int(match.group(2))
    return None


def parse_settings(lines: tuple[str, ...] | list[str]) -> dict[int, float]:
    """``$$`` output (``$100=80.000``...) as numbers; other lines are ignored."""
    settings: dict[int, float] = {}
    for line in lines:
        match = _SETTING.match(line.strip())
        if match:
            settings[int(match.group(1))] = float(match.group(2))
    return settings


# $11 junction deviation, $20 soft limits stay motiond's, $32 laser mode, then per axis
# steps/mm, max rate (mm/min), acceleration (mm/s²) and travel (mm).
ADOPTED_SETTINGS = (11, 32)
AXIS_SETTINGS = (100, 110, 120, 130)


def adopted_numbers(axis_count: int) -> list[int]:
    """The ``$`` settings motiond takes from the controller, for ``axis_count`` axes."""
    return [*ADOPTED_SETTINGS,
            *(base + index for base in AXIS_SETTINGS for index in range(axis_count))]


def mismatches(
    controller: Mapping[int, float], ours: Mapping[int, float], numbers: list[int]
) -> list[tuple[int, float, float]]:
    """``(number, ours, controller's)`` for each adopted setting on which the two differ
    (relative tolerance 1e-6: the controller prints three decimals)."""
    found = []
    for number in numbers:
        if number not in controller or number not in ours:
            continue
        theirs, mine = float(controller[number]), float(ours[number])
        if abs(theirs - mine) > 1e-6 * max(1.0, abs(theirs), abs(mine)) + 5e-4:
            found.append((number, mine, theirs))
    return found
