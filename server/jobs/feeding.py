"""A playing job's lines into the dispatcher: runs of plain lines at once, the others one by one.

Each batch of lines read from the file (:func:`~server.jobs.reading.read_batches`) is parsed
at once for its spans of plain lines (:func:`~server.gcode.plain.plain_spans`: ``G1 X12.3
S380``, a raster's millions); the dispatcher runs up to :data:`RUN_LINES` of them at a time
(:meth:`~server.runtime.dispatcher.Dispatcher.begin_run`): the machine reads as many as the
planner has room for with numpy and appends their blocks at once, the very blocks and state
the lines one by one give, for a fraction of the Python
(:meth:`~server.machine.feed.GcodeFeed.feed_plain`, which reads a run only where it pays: short
lines, and room for enough of them). Every other line, a line the machine does not take in a
run, and every line when the machine takes no runs (a Grbl controller takes each line as
sent), goes alone through :meth:`~server.runtime.dispatcher.Dispatcher.begin`, as a sender's
would; after a run that read nothing, lines go one by one until one waits for room. Nothing is
read ahead of the planner, so a line waiting to interject
(:class:`~server.jobs.interjections.Interjections`: a baby-step) runs between lines or runs, in
the job's order, as soon as it would between lines one by one. The first refused line stops
the job: :class:`LineFailed` names it.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from server.errors import CommandError
from server.gcode.parser import check_length
from server.gcode.plain import plain_spans

if TYPE_CHECKING:
    import numpy as np

    from server.jobs.interjections import Interjections
    from server.runtime.dispatcher import Dispatcher

YIELD_AFTER_S = 0.0003  # the job feeder gives other tasks a turn at least this often
RUN_LINES = 256  # plain lines run at once at most (an interjection waits this many at most)
Pending = deque[tuple[int, "asyncio.Future[list[str]]"]]


class JobSource(Protocol):
    name: str
    ticket: int  # the stop generation the job started in: its lines carry it
    can_control: bool


class Progress(Protocol):
    lines_done: int
    lines_total: int
    percent: float


class LineFailed(Exception):
    """The job stops: ``text`` names the line and why (``line 12: error:20 ...``)."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text


class JobFeeder:
    """Sends a job's lines, batch after batch (see the module docstring)."""

    def __init__(self, dispatcher: Dispatcher, source: JobSource, interjections: Interjections,
                 progress: Progress, limit_bytes: int, axes: Sequence[str],
                 runs: bool) -> None:
        self._dispatcher = dispatcher
        self._source = source
        self._interjections = interjections
        self._progress = progress
        self._limit_bytes = limit_bytes
        self._axes = axes
        self._runs = runs
        self._pending: Pending = deque()  # lines answered downstream, answers to come
        self._number = 0  # the lines sent
        self._turn_s = 0.0

    async def feed(self, batches: AsyncIterator[list[str]]) -> None:
        """Every line of ``batches`` sent and its answer come; raises :class:`LineFailed`."""
        self._turn_s = time.monotonic()
        async for batch in batches:
            index = 0
            if self._runs:
                columns, spans = plain_spans(batch, self._axes, self._limit_bytes)
                for start, stop in spans:
                    while index < start:
                        await self._line(batch[index])
                        index += 1
                    trying = True  # a run, until one reads nothing: then lines until one
                    while index < stop:  # waits (for room: a run may fit after it)
                        if trying:
                            read = await self._run(columns, index, min(stop, index + RUN_LINES))
                            if read:
                                index += read
                                continue
                        trying = await self._line(batch[index])
                        index += 1
            for line in batch[index:] if index else batch:
                await self._line(line)
        try:
            await self._interjections.run(self._as_job)
            await _settle(self._pending, wait=True)
        except CommandError as exc:
            raise LineFailed(f"line {self._number}: error:{exc.code} {exc.message}") from exc

    async def _line(self, line: str) -> bool:
        """Send one line; whether it waited (for its turn, or for room in the planner)."""
        self._number += 1
        number = self._number
        try:
            if self._interjections.waiting:  # a requester's line, in the job's order
                await self._interjections.run(self._as_job)
            check_length(line, self._limit_bytes)  # error 11, as a stream refuses it
            # (submit, without its coroutine for the line that needs no wait: most)
            source, pending = self._source, self._pending
            outcome = self._dispatcher.begin(line, source, source.ticket,
                                             _deferring(pending, number))
            waited = False
            if not isinstance(outcome, list):
                waited = True
                await outcome
            if pending:
                await _settle(pending, wait=False)
        except CommandError as exc:
            raise LineFailed(f"line {number}: error:{exc.code} {exc.message}") from exc
        if self._done(number):
            await asyncio.sleep(0)
        return waited

    async def _run(self, columns: dict[str, np.ndarray], start: int, stop: int) -> int:
        """Lines ``start`` to ``stop`` of the batch as a run: how many were read (0: none)."""
        try:
            if self._interjections.waiting:
                await self._interjections.run(self._as_job)
            source = self._source
            outcome = self._dispatcher.begin_run(columns, start, stop, source, source.ticket)
            read = outcome if isinstance(outcome, int) else await outcome
        except CommandError as exc:
            raise LineFailed(f"line {self._number + 1}: error:{exc.code} {exc.message}"
                             ) from exc
        if read and self._done(self._number + read):
            await asyncio.sleep(0)
        return read

    def _done(self, number: int) -> bool:
        """Lines up to ``number`` sent (the progress); whether to give the others a turn now
        (lines that never wait must not hog the loop)."""
        self._number = number
        progress = self._progress
        progress.lines_done = number
        progress.percent = min(100.0, 100.0 * number / max(1, progress.lines_total))
        now_s = time.monotonic()
        if now_s - self._turn_s > YIELD_AFTER_S:
            self._turn_s = now_s
            return True
        return False

    def _as_job(self, text: str, ticket: int) -> Awaitable[list[str]]:
        return self._dispatcher.submit(text, self._source, ticket)


def _deferring(pending: Pending, number: int) -> Callable[[asyncio.Future[list[str]]], None]:
    """The ``defer`` of line ``number``: its answer-to-come joins ``pending``."""
    return lambda future: pending.append((number, future))


async def _settle(pending: Pending, *, wait: bool) -> None:
    """Drop the deferred answers that came (all of them, waiting, with ``wait``); raise
    :class:`LineFailed` naming the first line the controller refused."""
    while pending and (wait or pending[0][1].done()):
        number, future = pending[0]
        try:
            await future
        except CommandError as exc:
            raise LineFailed(f"line {number}: error:{exc.code} {exc.message}") from exc
        pending.popleft()
