"""Lines run between a playing job's lines, as part of the job (Klipper's baby-steps).

A requester that must change the machine in order with a running or paused job's motion
(``SET_GCODE_OFFSET Z_ADJUST=.. MOVE=1`` from a Klipper front-end: an ``M290`` line) cannot
send its line as another source: the job owns the machine until it ends (error 45). It hands
the line to the job instead (:meth:`Interjections.add`); the job's player runs it before its
next line (:meth:`Interjections.run`), as the job's source, with the ordered stream's back-
pressure, so it takes effect exactly there: after the moves already queued, before the next.

The stop rule holds: each line carries the ticket it was asked in, and the dispatcher refuses
it once a stop has come (error 45), whatever it waited for. Each line runs at most once: its
future says what became of it — the line's messages, the error that refused it, or ``None``
when the job ended before the line's turn (nothing ran: the requester may now run it as any
other line, still under its ticket).
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from server.errors import CommandError, Error

PENDING_LINES = 8  # lines waiting for a job's next turn; beyond, error 45 at once
Submit = Callable[[str, int], Awaitable[list[str]]]  # (text, ticket) -> the line's messages


@dataclass(frozen=True, slots=True)
class _Line:
    text: str
    ticket: int  # the stop generation it was asked in
    answer: asyncio.Future[list[str] | None]


class Interjections:
    """The lines waiting for a job's next turn (bounded; one job's at a time)."""

    def __init__(self) -> None:
        self.waiting: deque[_Line] = deque()  # the player checks it before each of its lines

    def add(self, text: str, ticket: int) -> asyncio.Future[list[str] | None]:
        """Queue ``text`` for the job's next turn; raises CommandError 45 when
        :data:`PENDING_LINES` wait already."""
        if len(self.waiting) >= PENDING_LINES:
            raise CommandError(Error.BUSY, "too many lines wait for the job's next turn")
        answer: asyncio.Future[list[str] | None] = asyncio.get_running_loop().create_future()
        self.waiting.append(_Line(text, ticket, answer))
        return answer

    async def run(self, submit: Submit) -> None:
        """Run the waiting lines in order (the job's turn); each one's answer is set. A line
        interrupted (the job aborted while it waited for room) answers error 45: it may have
        taken effect in part (the interpreter read it), so it is never offered again."""
        while self.waiting:
            line = self.waiting.popleft()
            if line.answer.done():  # the requester gave up waiting
                continue
            try:
                messages = await submit(line.text, line.ticket)
            except CommandError as exc:
                _answer(line, exc)
            except BaseException:
                _answer(line, CommandError(Error.BUSY, "the job was stopped while the line ran"))
                raise
            else:
                _answer(line, messages)

    def release(self) -> None:
        """The job ended: the lines still waiting did not run (their answer is ``None``)."""
        while self.waiting:
            line = self.waiting.popleft()
            _answer(line, None)


def _answer(line: _Line, outcome: list[str] | CommandError | None) -> None:
    """Settle a line's answer, unless its requester stopped waiting for it."""
    if line.answer.done():
        return
    if isinstance(outcome, CommandError):
        line.answer.set_exception(outcome)
    else:
        line.answer.set_result(outcome)
