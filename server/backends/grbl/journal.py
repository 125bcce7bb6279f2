"""Keeping motiond's interpreter in step with a Grbl board that refuses a line (pure).

motiond interprets every line before it sends it to the board (``[backend] kind = "grbl"``),
so its modal state, offsets and position move on at once, while the board answers later: with
character counting several more lines may be interpreted and sent before the board's
``error:N`` for an earlier one arrives. Grbl 1.1 changes nothing for a line it refuses (its
parser works on a copy and commits only a valid block, checked on the rig), so neither may
motiond: :class:`SentLines` remembers, for each line sent and not yet answered, the
interpreter's state before it and how to interpret it again. When the board refuses one, the
interpreter goes back to that state and the lines sent after it are interpreted again from
there, as the board did (their own errors there are the board's to report).

A reset or a lost connection empties the board's buffer and resets the interpreter: the
journal is cleared (:meth:`SentLines.clear`) and late answers find nothing to undo.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from server.errors import CommandError
from server.gcode.interpreter import Interpreter, InterpreterState

MAX_SENT_LINES = 1024  # a Grbl buffer holds at most ~64 lines; beyond this, forget the oldest


@dataclass(slots=True, eq=False)
class Sent:
    """One line sent to the board: the interpreter's state before it, and how to redo it."""

    before: InterpreterState
    redo: Callable[[], object]


class SentLines:
    """The journal of lines the board has not answered yet; see the module docstring."""

    def __init__(self, interpreter: Callable[[], Interpreter]) -> None:
        self._interpreter = interpreter  # the machine's (check mode swaps it)
        self._lines: deque[Sent] = deque(maxlen=MAX_SENT_LINES)
        self.undone = 0  # lines the board refused after motiond had interpreted them

    def __len__(self) -> int:
        return len(self._lines)

    def add(self, before: InterpreterState, redo: Callable[[], object]) -> Sent:
        """A line was just interpreted (from ``before``) and goes to the board."""
        entry = Sent(before, redo)
        self._lines.append(entry)
        return entry

    def answered(self, entry: Sent) -> None:
        """The board accepted ``entry``: nothing to undo any more."""
        if entry in self._lines:
            self._lines.remove(entry)

    def refused(self, entry: Sent) -> None:
        """The board refused ``entry`` (or it never reached the board): the interpreter as if
        it had never been read, then the lines sent after it read again, in order."""
        if entry not in self._lines:
            return  # a reset since: the interpreter was reset too
        index = self._lines.index(entry)
        self._lines.remove(entry)
        self.undone += 1
        interpreter = self._interpreter()
        interpreter.restore(entry.before)
        for later in list(self._lines)[index:]:
            later.before = interpreter.save()
            try:
                later.redo()
            except CommandError:  # refused here too: its own answer from the board will say
                later.redo = _nothing

    def clear(self) -> None:
        self._lines.clear()


def _nothing() -> None:
    """A line that changed nothing when it was read again."""
