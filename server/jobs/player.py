"""A playing job's lines sent through the dispatcher, as a sender's are.

:func:`send_lines` gives the dispatcher each line of the file in order, the job's source and
ticket on each (a stop refuses every line after it, error 45), with the back-pressure of a
full planner, and runs the lines another requester hands the job (:mod:`.interjections`)
between them. A run of plain lines (``G1 X.. Y.. S..``: most of a raster) goes as a span
(:func:`~server.gcode.plain.plain_items`, ``Dispatcher.begin_span``): read at once by the
interpreter and queued as the planner has room, the same outputs as its lines one by one at
a few microseconds a line less. A line a Grbl controller downstream answers later is
deferred: the job sends on and stops at the first answer that is an error.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TYPE_CHECKING, Protocol

from server.errors import CommandError
from server.gcode.parser import check_length
from server.gcode.plain import PlainSpan, plain_items

if TYPE_CHECKING:
    from server.config import CoreConfig
    from server.gcode.interpreter import Interpreter
    from server.jobs.interjections import Interjections
    from server.runtime.dispatcher import Dispatcher

YIELD_AFTER_S = 0.0003  # the player gives other tasks a turn at least this often
SPAN_CHUNK_LINES = 200  # lines looked at for spans at a time (the parse of a chunk and a
# span's reading each hold the loop a fraction of a millisecond)
Pending = deque[tuple[int, "asyncio.Future[list[str]]"]]  # deferred answers, by line


class Progress(Protocol):
    """Where the player counts the lines sent (a job's progress)."""

    lines_total: int
    lines_done: int
    percent: float


class JobSource(Protocol):
    """The job's source, with the stop generation its lines carry."""

    name: str
    can_control: bool
    ticket: int


async def send_lines(batches: AsyncIterator[list[str]], progress: Progress, source: JobSource,
                     dispatcher: Dispatcher, interpreter: Callable[[], Interpreter],
                     core: CoreConfig, interjections: Interjections) -> str | None:
    """Send every line of ``batches`` and wait for their answers; the failure (``line N:
    error:..``) that stopped the job, or None. ``interpreter()``: the machine's, as it is."""
    begin, begin_span = dispatcher.begin, dispatcher.begin_span
    loop = asyncio.get_running_loop()
    turn_s = loop.time()
    limit, axes = core.protocol.line_limit, core.axis_names
    pending: Pending = deque()
    waiting = interjections.waiting  # (a deque's truth costs a fifth of a method's)

    def as_job(text: str, ticket: int) -> Awaitable[list[str]]:
        return dispatcher.submit(text, source, ticket)

    def takes_runs() -> bool:  # (the machine's interpreter as it is when asked)
        return dispatcher.reads_spans and interpreter().takes_runs()

    def hurry() -> bool:  # a requester's line waits: a span stops at the next line
        return bool(waiting)

    base = 0
    async for batch in batches:
        for first in range(0, len(batch), SPAN_CHUNK_LINES):
            chunk = batch[first : first + SPAN_CHUNK_LINES]
            for item in plain_items(chunk, axes, limit, takes_runs):
                if loop.time() - turn_s > YIELD_AFTER_S:  # lines that never wait must not
                    await asyncio.sleep(0)  # hog the loop (asked before each line or span:
                    turn_s = loop.time()  # a chunk's parse, then its first span's reading)
                try:
                    if waiting:  # a requester's line, in the job's order (a baby-step)
                        await interjections.run(as_job)
                    if type(item) is int:
                        number, line = base + item + 1, chunk[item]
                        check_length(line, limit)  # error 11, as a stream refuses it
                        # (submit, without its coroutine for the line that needs no wait)
                        outcome = begin(line, source, source.ticket,
                                        _deferring(pending, number))
                    else:  # a span of plain lines: a refusal names its first line
                        assert isinstance(item, PlainSpan)
                        number = base + item.start + 1
                        item.hurry = hurry
                        outcome = begin_span(item, source, source.ticket)
                    if not isinstance(outcome, list):
                        await outcome
                        if type(item) is not int:  # a span that waited for room: the loop
                            turn_s = loop.time()  # ran the others meanwhile
                    if pending:
                        await _settle(pending, wait=False)
                except _LineFailed as failed:
                    return failed.text
                except CommandError as exc:
                    return f"line {number}: error:{exc.code} {exc.message}"
                if isinstance(item, PlainSpan):
                    number = base + item.start + item.taken
                progress.lines_done = number
                progress.percent = min(100.0, 100.0 * number / max(1, progress.lines_total))
            base += len(chunk)
    try:
        await interjections.run(as_job)
        await _settle(pending, wait=True)
    except _LineFailed as failed:
        return failed.text
    return None


def _deferring(pending: Pending, number: int) -> Callable[[asyncio.Future[list[str]]], None]:
    """The ``defer`` of line ``number``: its answer-to-come joins ``pending``."""
    return lambda future: pending.append((number, future))


class _LineFailed(Exception):
    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text


async def _settle(pending: Pending, *, wait: bool) -> None:
    """Drop the deferred answers that came (all of them, waiting, with ``wait``); raise
    :class:`_LineFailed` naming the first line the controller refused."""
    while pending and (wait or pending[0][1].done()):
        number, future = pending[0]
        try:
            await future
        except CommandError as exc:
            raise _LineFailed(f"line {number}: error:{exc.code} {exc.message}") from exc
        pending.popleft()
