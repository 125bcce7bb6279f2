"""The dispatcher: one ordered command stream shared by every input source.

Every line from every connection and job goes through :meth:`Dispatcher.submit`, which holds a
FIFO lock for the whole execution of the line, so commands run strictly in arrival order and a
line waiting for planner room holds back the lines behind it (that is the back-pressure).

Lines are routed by their form:
  * ``$...`` to the ``$`` command handlers (``$H``, ``$J``, ``$$``, ``$=`` for ``$100=80``);
  * a leading word of two or more letters (``version``, ``fire 50``) to named commands;
  * everything else is parsed as G-code: a G/M code with a registered handler (``M106``)
    goes to that handler, the rest to the G-code interpreter handler.

A handler returns the message lines to send before ``ok`` (or None) and raises
:class:`CommandError` to answer ``error:N``. Several handlers may share a name; all run, in
registration order. An unknown command is an error for its sender, never a silent no-op.
"""

from __future__ import annotations

import asyncio
import inspect
import re
from collections import defaultdict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Protocol

from server.errors import BUSY, UNKNOWN_COMMAND, CommandError
from server.gcode import Line, parse_line

HandlerResult = list[str] | None
Handler = Callable[["Command"], Awaitable[HandlerResult] | HandlerResult]

_NAMED = re.compile(r"([A-Za-z][A-Za-z_\-]+)(?:\s+(.*))?$", re.S)
_DOLLAR = re.compile(r"\$([$#]|[A-Za-z]*)\s*(.*)$", re.S)
_SETTING = re.compile(r"\$(\d+)\s*=\s*(.*)$")
_STARTUP = re.compile(r"\$[Nn](\d)\s*=(.*)$", re.S)
LOCKED_OUT = 9
INVALID_DOLLAR = 3


class Source(Protocol):
    """Whoever sent a line: a connection or a job player."""

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
    """

    name: str
    text: str
    args: str
    source: Source
    line: Line | None = None


@dataclass(slots=True)
class _Entry:
    handlers: list[Handler] = field(default_factory=list)
    when_locked: bool = False


class Dispatcher:
    """Routes lines to handlers, one at a time, in order."""

    def __init__(self, is_locked: Callable[[], bool] = lambda: False) -> None:
        self._entries: defaultdict[str, _Entry] = defaultdict(_Entry)
        self._gcode: Handler | None = None
        self._lock = asyncio.Lock()
        self._is_locked = is_locked
        self._closed = False
        self._immediate: set[str] = set()

    def register(self, name: str, handler: Handler, *, when_locked: bool = False) -> None:
        """Add a handler for ``name`` (``M106``, ``$H``, ``fire``).

        ``when_locked`` lets it run while the machine is in ALARM.
        """
        entry = self._entries[_key(name)]
        entry.handlers.append(handler)
        entry.when_locked = entry.when_locked or when_locked

    def set_gcode_handler(self, handler: Handler) -> None:
        """The handler for G-code lines no registered G/M handler claims (the interpreter)."""
        self._gcode = handler

    def names(self) -> list[str]:
        """Every registered command name."""
        return sorted(self._entries)

    def close(self) -> None:
        """Shutdown: refuse every line from now on."""
        self._closed = True

    def register_immediate(self, name: str, handler: Handler) -> None:
        """A named command that runs at once, outside the ordered stream (job control:
        ``suspend``, ``resume``, ``abort`` must work while a held job waits for room)."""
        self.register(name, handler, when_locked=True)
        self._immediate.add(_key(name))

    async def submit(
        self, text: str, source: Source, still_valid: Callable[[], bool] | None = None
    ) -> list[str]:
        """Execute one line in order with every other source; returns messages for the reply.

        ``still_valid`` is checked once the line's turn comes: a line overtaken by a reset of
        its connection while it waited is dropped (CommandError BUSY), never run late.
        """
        if self._closed:
            raise CommandError(BUSY, "shutting down")
        named = _NAMED.match(text.strip())
        if named and _key(named.group(1)) in self._immediate:
            return await self.execute(text, source)
        async with self._lock:
            if self._closed:
                raise CommandError(BUSY, "shutting down")
            if still_valid is not None and not still_valid():
                raise CommandError(BUSY, "overtaken by a reset")
            return await self.execute(text, source)

    async def execute(self, text: str, source: Source) -> list[str]:
        """Execute one line now (the caller holds the order); raise CommandError to refuse it."""
        stripped = text.strip()
        if not stripped:
            return []
        if not source.can_control and not _is_query(stripped):
            raise CommandError(46, "this connection is read-only")
        if stripped.startswith("$"):
            return await self._dollar(stripped, text, source)
        named = _NAMED.match(stripped)
        if named and _key(named.group(1)) in self._entries:
            return await self._run(
                _key(named.group(1)),
                Command(_key(named.group(1)), text, named.group(2) or "", source),
            )
        return await self._gcode_line(text, source)

    async def _dollar(self, stripped: str, text: str, source: Source) -> list[str]:
        setting = _SETTING.match(stripped)
        if setting:
            return await self._run("$=", Command("$=", text, stripped[1:], source))
        startup = _STARTUP.match(stripped)
        if startup:
            name = f"$N{startup.group(1)}="
            return await self._run(name, Command(name, text, startup.group(2), source))
        match = _DOLLAR.match(stripped)
        if match is None:
            raise CommandError(3, f"invalid $ statement {stripped!r}")
        word, rest = match.group(1).upper(), match.group(2)
        if "=" in word or rest.startswith("="):
            name, args = f"${word}=", rest.lstrip("=")
        else:
            name, args = f"${word}", rest
        if name not in self._entries:
            raise CommandError(3, f"unknown $ command {name}")
        return await self._run(name, Command(name, text, args, source))

    async def _gcode_line(self, text: str, source: Source) -> list[str]:
        line = parse_line(text)
        if line.error is not None:
            raise line.error
        for letter, value in zip(line.letters, line.values):  # noqa: B905 - parallel lists
            if letter in "GM":
                name = f"{letter}{value:g}"
                if name in self._entries:
                    return await self._run(name, Command(name, text, "", source, line))
        if not line.letters:
            return []
        if self._is_locked():
            raise CommandError(LOCKED_OUT, "G-code locked out during alarm: $X or M999 to unlock")
        if self._gcode is None:
            raise CommandError(20, "no G-code interpreter")
        return await _call(self._gcode, Command("G", text, "", source, line))

    async def _run(self, name: str, command: Command) -> list[str]:
        entry = self._entries.get(name)
        if entry is None:
            code = INVALID_DOLLAR if name.startswith("$") else UNKNOWN_COMMAND
            raise CommandError(code, f"unknown command {name}")
        if self._is_locked() and not entry.when_locked:
            raise CommandError(LOCKED_OUT, f"{name} locked out during alarm: $X or M999 to unlock")
        messages: list[str] = []
        for handler in entry.handlers:
            messages += await _call(handler, command)
        return messages


async def _call(handler: Handler, command: Command) -> list[str]:
    result = handler(command)
    if inspect.isawaitable(result):
        result = await result
    return list(result or ())


def _key(name: str) -> str:
    """Normalise a command name: G/M codes and $ commands upper-case, named commands lower-case."""
    if name.startswith("$"):
        return name.upper()
    if len(name) > 1 and name[0] in "GMgm" and name[1:].replace(".", "", 1).isdigit():
        return f"{name[0].upper()}{float(name[1:]):g}"
    return name.lower()


_QUERIES = frozenset(
    {
        "$",
        "$$",
        "$#",
        "$G",
        "$I",
        "$N",
        "?",
        "VERSION",
        "M114",
        "M119",
        "M105",
        "M115",
        "PROGRESS",
        "LS",
    }
)


def _is_query(stripped: str) -> bool:
    return stripped.upper().split(" ")[0] in _QUERIES
