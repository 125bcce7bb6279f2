"""Reading a job file as it plays: never whole, file I/O in threads, the estimate stoppable.

:func:`read_lines` gives the lines to the player :data:`READ_LINES` at a time, read in a thread;
:func:`estimate_file` runs :func:`~server.offline.estimate.estimate` over the file as it reads
it (in a thread of its own), and gives up as soon as its ``stop`` event is set (the job ended).
Memory is bounded by a batch of lines and the planner's window, whatever the file's size.
"""

from __future__ import annotations

import asyncio
import itertools
import threading
from collections.abc import AsyncGenerator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from server.offline.estimate import estimate, file_lines
from server.offline.stats import JobStats

if TYPE_CHECKING:
    from server.config import CoreConfig
    from server.gcode.interpreter import Interpreter

READ_LINES = 1000  # a job file is read this many lines at a time (in a thread)


class Progress(Protocol):
    percent: float


async def read_lines(
    path: Path, limit_chars: int, progress: Progress
) -> AsyncGenerator[str, None]:
    """The file's lines (see :func:`file_lines`); ``progress.percent`` follows the characters
    read (close the generator, ``contextlib.aclosing``, to close the file early)."""
    size = max(1, (await asyncio.to_thread(path.stat)).st_size)
    handle = await asyncio.to_thread(path.open, errors="replace")
    try:
        lines = file_lines(handle, limit_chars)
        read_chars = 0
        while batch := await asyncio.to_thread(_take, lines, READ_LINES):
            for line in batch:
                read_chars += len(line) + 1
                progress.percent = min(99.9, 100.0 * read_chars / size)
                yield line
    finally:
        handle.close()


def estimate_file(
    path: Path, core: CoreConfig, interpreter: Interpreter, stop: threading.Event
) -> JobStats | None:
    """In a thread: :func:`estimate` over the file's lines as they are read; None when
    ``stop`` was set first."""
    with path.open(errors="replace") as handle:
        try:
            return estimate(_until(file_lines(handle, core.protocol.line_limit), stop), core,
                            None, interpreter)
        except _Stopped:
            return None


class _Stopped(Exception):
    """The job ended: its estimate is no longer wanted."""


def _take(lines: Iterator[str], count: int) -> list[str]:
    """Up to ``count`` more lines (in a thread: it reads the file)."""
    return list(itertools.islice(lines, count))


def _until(lines: Iterator[str], stop: threading.Event) -> Iterator[str]:
    for number, line in enumerate(lines):
        if number % READ_LINES == 0 and stop.is_set():
            raise _Stopped
        yield line
