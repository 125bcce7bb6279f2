"""The dispatcher: one ordered command stream shared by every input source.

Every line from every connection and job goes through :meth:`Dispatcher.submit`, which holds a
FIFO lock for the whole execution of the line, so commands run strictly in arrival order and a
line waiting for planner room holds back the lines behind it (that is the back-pressure).

Lines are routed by their form:
  * ``$...`` to the ``$`` command handlers (``$H``, ``$J``, ``$$``, ``$=`` for ``$100=80``);
  * a leading word of two or more letters (``version``, ``fire 50``) to named commands;
  * ``M113``, ``M117``, ``M118`` (RepRap keep-alive, display and echo) to their handlers, the
    rest of the line text (``M117 Done!`` is no G-code: the parser would read ``D``, ``o``...);
  * everything else is G-code, interpreted once, whole, by the G-code handler (the machine's
    interpreter, where modules register the M-codes they own: see :mod:`server.gcode.codes`).

Whether a line may run is decided from all of it: a ``$`` or named command is a query when
registered as one, a G-code line when the interpreter classifies every word of it as a report
(:meth:`Interpreter.classify`). A read-only source runs queries only. While the machine runs
motion that one source queued (a job, or a stream), other sources may query but not change
anything (error 45); realtime hold and reset stay open to every controlling connection.

A handler returns the message lines to send before ``ok`` (or None) and raises
:class:`CommandError` to answer ``error:N``. A caller that can answer later passes ``defer``
(a session, a job): a handler whose line is answered by something downstream (a Grbl controller
behind motiond) hands it the future of that answer and returns at once, so the next line can be
sent while this one is in the controller's buffer; the caller replies once the future is done,
in the order it submitted the lines. Without ``defer`` the handler waits for the answer itself.
Several handlers may share a name; all run, in registration order. An unknown command is an
error for its sender, never a silent no-op.

Every line carries the stop generation it was sent in (its ``ticket``: a session's line the one
it arrived in, anything else the one it was submitted in; see :mod:`server.runtime.state`). A
line whose ticket a stop has made void is refused where it would start, once its turn comes
(error 45, never run late); a handler that waits inside its line (a job's fit check, a deferred
jog) finds the ticket on its :class:`Command` and checks it before it acts.

A line that needs no wait runs to its end inside :meth:`Dispatcher.begin`, with no task switch,
future or lock object on its way (a raster streams hundreds of such lines a second): a handler
may return its messages, or an awaitable of them when it must wait (the planner is full, a
sync request); only then does the line hold its turn across awaits.
"""

from __future__ import annotations

import asyncio
import inspect
import math
import re
import string
import time
from collections import defaultdict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from server.errors import CommandError, Error
from server.gcode.interpreter import LineKind
from server.gcode.parser import Line, parse_line
from server.gcode.plain import PlainSpan
from server.runtime.turn import Turn

HandlerResult = list[str] | None
Outcome = list[str] | Awaitable[list[str]]  # a line's messages, or the wait for them
Deferred = Callable[["asyncio.Future[list[str]]"], None]  # takes a line's answer-to-come
Handler = Callable[["Command"], Awaitable[HandlerResult] | HandlerResult]
Classifier = Callable[[Line], LineKind]
SpanHandler = Callable[[PlainSpan], Outcome]  # reads and queues a span (sets its ``taken``)

_NAMED = re.compile(r"([A-Za-z][A-Za-z_\-]+)(?:\s+(.*))?$", re.S)
_NAME_LETTERS = frozenset(string.ascii_letters + "_-")  # a name's second character
_GM_NAME = re.compile(r"[GMgm]\d")
_GRBL_DOLLAR_LETTERS = "$#CGHIJNRSX"  # Grbl 1.1's $ commands: $$ $# $C $G $H $I $J= $N $RST $SLP $X
_DOLLAR = re.compile(r"\$([$#]|[A-Za-z]*)\s*(.*)$", re.S)
_SETTING = re.compile(r"\$(\d+)\s*=\s*(.*)$")
_STARTUP = re.compile(r"\$[Nn](\d)\s*=(.*)$", re.S)
_TEXT_CODE = re.compile(r"[Mm]0*(113|117|118)(?![\d.])\s?(.*)$", re.S)
_QUERY, _EFFECT = LineKind.QUERY, LineKind.EFFECT  # (an enum member's look-up costs a call)
TEXT_CODES = frozenset({"M113", "M117", "M118"})  # M-codes whose rest of line is text, not words


class Source(Protocol):
    """Whoever sent a line: a connection or a job player.

    A source may also say ``soft_limit_alarms = False`` (a RepRap host's session): its line
    with a target outside the travel is refused without Grbl's ALARM:2; ``dwell_waits = True``
    (a Grbl session): its ``G4`` is answered once the motion before it and the dwell have run;
    and it may have a ``busy_interval_s`` (a session), which M113 sets.
    """

    name: str
    can_control: bool


@dataclass(slots=True)
class SystemSource:
    """A source inside the server (startup lines, tests)."""

    name: str = "system"
    can_control: bool = True


@dataclass(slots=True)
class Command:
    """One command as a handler sees it.

    Attributes:
        name: the routing key: ``G28.2``, ``M106``, ``$H``, ``$=`` (setting), ``fire``.
        text: the whole line as received.
        args: text after the command name (``$`` and named commands).
        line: the parsed G-code line (G/M handlers only).
        source: who sent it.
        defer: set when the caller can take the line's answer later (see the module docstring).
        ticket: the stop generation the line was sent in (a handler that waits checks it).
    """

    name: str
    text: str
    args: str
    source: Source
    line: Line | None = None
    defer: Deferred | None = None
    ticket: int = 0


@dataclass(slots=True)
class _Entry:
    handlers: list[Handler] = field(default_factory=list)
    when_locked: bool = False
    query: bool = False


class Dispatcher:
    """Routes lines to handlers, one at a time, in order.

    ``is_locked`` says whether the machine is locked out (ALARM, Sleep), ``locked_by`` what
    locks it (``ALARM:40 (Halt ...)``: a refused line names it); ``is_busy`` whether
    queued motion is still running (the source that queued it owns the machine until then);
    ``stops`` the stop generation now (the tickets lines are checked against).
    """

    def __init__(
        self,
        is_locked: Callable[[], bool] = lambda: False,
        is_busy: Callable[[], bool] = lambda: False,
        stops: Callable[[], int] = lambda: 0,
        locked_by: Callable[[], str] = lambda: "alarm",
    ) -> None:
        self._locked_by = locked_by
        self._entries: defaultdict[str, _Entry] = defaultdict(_Entry)
        self._gcode: Handler | None = None
        self._spans: SpanHandler | None = None
        self._classify: Classifier = lambda line: LineKind.EFFECT
        self._turn = Turn()
        self._is_locked = is_locked
        self._is_busy = is_busy
        self.stops = stops
        self._owner: Source | None = None
        self._closed = False
        self._immediate: set[str] = set()
        self.last_command_s = -math.inf  # time.monotonic() of the latest submit()

    def register(
        self, name: str, handler: Handler, *, when_locked: bool = False, query: bool = False
    ) -> None:
        """Add a handler for a ``$`` command (``$H``) or a named command (``fire``).

        ``when_locked`` lets it run while the machine is in ALARM; ``query`` marks a command
        that only reports, which read-only sources may run. G and M codes belong to the
        interpreter (modules claim M-codes with :meth:`CodeTable.register`).
        """
        if _GM_NAME.match(name) and name.upper() not in TEXT_CODES:
            raise ValueError(f"{name}: G and M codes are registered with the interpreter")
        entry = self._entries[_key(name)]
        entry.handlers.append(handler)
        entry.when_locked = entry.when_locked or when_locked
        entry.query = entry.query or query

    def set_gcode_handler(self, handler: Handler, classify: Classifier | None = None,
                          spans: SpanHandler | None = None) -> None:
        """The handler of every G-code line (the machine), what decides what a line does
        (without it, every line is an effect: read-only sources may run none) and, where the
        machine reads a job's plain lines at once, the handler of their spans."""
        self._gcode, self._spans = handler, spans
        if classify is not None:
            self._classify = classify

    def names(self) -> list[str]:
        """Every registered command name."""
        return sorted(self._entries)

    def close(self) -> None:
        """Shutdown: refuse every line from now on."""
        self._closed = True

    def register_immediate(self, name: str, handler: Handler, *, query: bool = False) -> None:
        """A named command that runs at once, outside the ordered stream (job control:
        ``suspend``, ``resume``, ``abort`` must work while a held job waits for room)."""
        self.register(name, handler, when_locked=True, query=query)
        self._immediate.add(_key(name))

    async def submit(
        self,
        text: str,
        source: Source,
        ticket: int | None = None,
        defer: Deferred | None = None,
    ) -> list[str]:
        """Execute one line in order with every other source; returns messages for the reply.

        ``ticket`` (default: now) is checked once the line's turn comes: a line a stop has
        overtaken while it waited is dropped (CommandError Error.BUSY), never run late.
        """
        outcome = self.begin(text, source, ticket, defer)
        return outcome if isinstance(outcome, list) else await outcome

    def begin(
        self,
        text: str,
        source: Source,
        ticket: int | None = None,
        defer: Deferred | None = None,
    ) -> Outcome:
        """:meth:`submit`, run as far as it goes without waiting: the line's messages when it
        is done, else an awaitable of them, which the caller must await at once (the line
        holds its turn until then). Raises CommandError as :meth:`submit` does."""
        if self._closed:
            raise CommandError(Error.BUSY, "shutting down")
        self.last_command_s = time.monotonic()
        if ticket is None:
            ticket = self.stops()
        stripped = text.strip()
        named = _named(stripped)
        if named and _key(named.group(1)) in self._immediate:
            return self._route(text, stripped, named, source, None, ticket)
        return self._in_order(ticket, self._route, text, stripped, named, source, defer, ticket)

    def begin_span(self, span: PlainSpan, source: Source, ticket: int) -> Outcome:
        """A span of a job's plain lines (:func:`~server.gcode.plain.plain_items`) as
        :meth:`begin` runs a line: in order, checked as one G-code line is (its source, the
        lock, the ticket), then read and queued by the span handler as far as the interpreter
        takes it (``span.taken``; none when the machine reads no spans, :attr:`reads_spans`)."""
        if self._closed:
            raise CommandError(Error.BUSY, "shutting down")
        self.last_command_s = time.monotonic()
        return self._in_order(ticket, self._span, span, source)

    @property
    def reads_spans(self) -> bool:
        """Whether :meth:`begin_span` reads spans (the machine's handler says so)."""
        return self._spans is not None

    def _in_order(self, ticket: int, route: Callable[..., Outcome], *args: Any) -> Outcome:
        """``route(*args)`` in its turn: at once when no other source's line holds it, with
        ``ticket`` checked (a line a stop overtook is not run)."""
        if not self._turn.free:
            return self._in_turn(ticket, route, args)
        if ticket != self.stops():  # (_check_ticket, without its call for every line)
            self._check_ticket(ticket)
        self._turn.taken = True
        try:
            outcome = route(*args)
        except BaseException:
            self._turn.release()
            raise
        if isinstance(outcome, list):
            self._turn.release()
            return outcome
        return self._then_release(outcome)

    def _check_ticket(self, ticket: int) -> None:
        if ticket != self.stops():
            raise CommandError(Error.BUSY, "a stop came after this line was sent: not run")

    async def _in_turn(self, ticket: int, route: Callable[..., Outcome],
                       args: tuple[Any, ...]) -> list[str]:
        """A line that waits for its turn behind another source's."""
        await self._turn.take()
        try:
            if self._closed:
                raise CommandError(Error.BUSY, "shutting down")
            self._check_ticket(ticket)
            outcome = route(*args)
            return outcome if isinstance(outcome, list) else await outcome
        finally:
            self._turn.release()

    def _span(self, span: PlainSpan, source: Source) -> Outcome:
        if source is not self._owner or not source.can_control:
            self._check_source(source, query=False)
        if self._is_locked():
            raise self._locked_out("G-code")
        if self._spans is None:
            return []  # (nothing taken: the caller reads the lines one by one)
        return self._spans(span)

    async def _then_release(self, outcome: Awaitable[list[str]]) -> list[str]:
        try:
            return await outcome
        finally:
            self._turn.release()

    async def execute(self, text: str, source: Source, defer: Deferred | None = None) -> list[str]:
        """Execute one line now (the caller holds the order); raise CommandError to refuse it."""
        stripped = text.strip()
        outcome = self._route(text, stripped, _named(stripped), source, defer, self.stops())
        return outcome if isinstance(outcome, list) else await outcome

    def _route(self, text: str, stripped: str, named: re.Match[str] | None,
               source: Source, defer: Deferred | None, ticket: int) -> Outcome:
        """:meth:`execute`, with the line stripped and matched as a named command already."""
        if not stripped:
            return []
        if stripped[0] == "$":
            name, args = _dollar_name(stripped)
            return self._run(name, Command(name, text, args, source, defer=defer, ticket=ticket))
        if named and _key(named.group(1)) in self._entries:
            name = _key(named.group(1))
            return self._run(name, Command(name, text, named.group(2) or "", source,
                                           ticket=ticket))
        text_code = _TEXT_CODE.match(stripped) if stripped[0] in "Mm" else None
        if text_code and f"M{text_code.group(1)}" in self._entries:
            name = f"M{text_code.group(1)}"
            return self._run(name, Command(name, text, text_code.group(2), source,
                                           ticket=ticket))
        return self._gcode_line(text, source, defer, ticket)

    def _gcode_line(self, text: str, source: Source, defer: Deferred | None,
                    ticket: int) -> Outcome:
        line = parse_line(text)
        if line.error is not None:
            raise line.error
        if not line.letters:
            return []
        kind = self._classify(line)
        if kind is not _QUERY and (source is not self._owner or not source.can_control):
            self._check_source(source, query=False)  # (the owner's next line: nothing to check)
        if kind is _EFFECT and self._is_locked():
            raise self._locked_out("G-code")
        if self._gcode is None:
            raise CommandError(Error.UNSUPPORTED, "no G-code interpreter")
        result = self._gcode(Command("G", text, "", source, line, defer, ticket))
        if type(result) is list:  # the common line: its messages, at once
            return result
        if inspect.isawaitable(result):
            return _listed(result)
        return list(result or ())

    async def _run(self, name: str, command: Command) -> list[str]:
        entry = self._entries.get(name)
        if entry is None:
            code = Error.UNKNOWN_COMMAND
            if name.startswith("$"):  # a letter Grbl has, badly used: 3; else Grbl reads a
                known = name[1:2] != "" and name[1:2] in _GRBL_DOLLAR_LETTERS  # number: 2
                code = Error.INVALID_STATEMENT if known else Error.BAD_NUMBER_FORMAT
            raise CommandError(code, f"unknown command {name}")
        self._check_source(command.source, query=entry.query, job_control=name in self._immediate)
        if self._is_locked() and not entry.when_locked:
            raise self._locked_out(name)
        messages: list[str] = []
        for handler in entry.handlers:
            messages += await _call(handler, command)
        return messages

    def _locked_out(self, what: str) -> CommandError:
        return CommandError(Error.LOCKED_OUT,
                            f"{what} locked out during {self._locked_by()}: $X or M999 to unlock")

    def _check_source(self, source: Source, *, query: bool, job_control: bool = False) -> None:
        """Queries run for anyone; anything else needs control, and (but to suspend, resume
        or abort a job) the machine's owner."""
        if query:
            return
        if not source.can_control:
            raise CommandError(Error.AUTH_REQUIRED, "this connection is read-only")
        if job_control:
            return
        owner = self._owner
        if owner is not None and owner is not source and self._is_busy():
            raise CommandError(Error.BUSY, f"the machine is running {owner.name}'s motion")
        self._owner = source

    def claim(self, source: Source) -> None:
        """``source`` (a job just started) owns the machine from now on."""
        self._owner = source


def _named(stripped: str) -> re.Match[str] | None:
    """``_NAMED.match(stripped)``, without the regular expression for a line whose second
    character rules a name out (every G-code line: ``G1``, ``M3``, ``X10``)."""
    if len(stripped) < 2 or stripped[1] not in _NAME_LETTERS:
        return None
    return _NAMED.match(stripped)


def _dollar_name(stripped: str) -> tuple[str, str]:
    """``$100=80`` -> (``$=``, ``100=80``); ``$J=G91 X1`` -> (``$J=``, ``G91 X1``)."""
    setting = _SETTING.match(stripped)
    if setting:
        return "$=", stripped[1:]
    startup = _STARTUP.match(stripped)
    if startup:
        return f"$N{startup.group(1)}=", startup.group(2)
    match = _DOLLAR.match(stripped)
    if match is None:
        raise CommandError(Error.INVALID_STATEMENT, f"invalid $ statement {stripped!r}")
    word, rest = match.group(1).upper(), match.group(2)
    if "=" in word or rest.startswith("="):
        return f"${word}=", rest.lstrip("=")
    return f"${word}", rest


async def _call(handler: Handler, command: Command) -> list[str]:
    result = handler(command)
    if inspect.isawaitable(result):
        result = await result
    return list(result or ())


async def _listed(result: Awaitable[HandlerResult]) -> list[str]:
    return list(await result or ())


def _key(name: str) -> str:
    """Normalise a command name: G/M codes and $ commands upper-case, named commands lower-case."""
    if name.startswith("$"):
        return name.upper()
    if len(name) > 1 and name[0] in "GMgm" and name[1:].replace(".", "", 1).isdigit():
        return f"{name[0].upper()}{float(name[1:]):g}"
    return name.lower()
