"""Reading a job file as it plays: never whole, file I/O in threads, its plan stoppable.

:func:`read_batches` gives the lines to the player :data:`READ_LINES` at a time, read in a thread;
:func:`until` lets a plan read through the file (:mod:`server.jobs.clock`) give up soon after
it is no longer wanted (within a chunk of the file). Memory is bounded by a
batch of lines and the planner's window, whatever the file's size.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import AsyncGenerator, Callable, Iterator
from pathlib import Path

from server.offline.estimate import file_lines

READ_LINES = 1000  # a job file is read this many lines at a time (in a thread)


async def read_batches(path: Path, limit_chars: int) -> AsyncGenerator[list[str], None]:
    """The file's lines (see :func:`file_lines`), :data:`READ_LINES` at a time (close the
    generator, ``contextlib.aclosing``, to close the file early)."""
    handle = await asyncio.to_thread(path.open, errors="replace")
    try:
        lines = file_lines(handle, limit_chars)
        while batch := await asyncio.to_thread(_take, lines, READ_LINES):
            yield batch
    finally:
        handle.close()


class Stopped(Exception):
    """The job ended (or was aborted before it started): its plan is no longer wanted."""


def _take(lines: Iterator[str], count: int) -> list[str]:
    """Up to ``count`` more lines (in a thread: it reads the file)."""
    return list(itertools.islice(lines, count))


def until(chunks: Iterator[list[str]], stopped: Callable[[], bool]) -> Iterator[str]:
    """The lines of ``chunks`` (:func:`~server.offline.estimate.file_chunks`), raising
    :class:`Stopped` soon after ``stopped()`` becomes true (asked before every chunk)."""
    for chunk in chunks:
        if stopped():
            raise Stopped
        yield from chunk
