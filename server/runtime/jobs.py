"""Stored job files: upload, list, play through the dispatcher, progress, abort, suspend.

Files live flat in the data folder's ``jobs/`` (:func:`server.paths.jobs_dir`). A name is a
plain file name: no folders, no ``..``, no leading dot, no control character and nothing
``str.splitlines`` splits on (a name is sent inside reply and pushed lines: ``\n``, ``\r``,
U+2028... would break them into several lines, a bare ``ok`` among them); Smoothie's ``/sd/``
prefix is accepted and dropped. A file on disk whose name breaks these rules is never listed.
Uploads are written to a hidden ``.upload-*`` file and renamed; such files left by a crash are
removed at start-up. Playing a file streams its lines through the same dispatcher a sender
uses, so the job is executed, flow-controlled and error-checked exactly like streamed G-code;
the first line that is refused stops the job with a message naming the line. A line answered
downstream (a Grbl controller) is deferred by the dispatcher: the job sends on while it is in
the controller's buffer and stops at the first answer that is an error. File I/O runs in a
thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import tempfile
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from server.errors import CommandError, Error
from server.gcode.parser import check_length
from server.offline.estimate import estimate, read_file_lines
from server.offline.stats import format_duration
from server.paths import jobs_dir
from server.runtime.dispatcher import Command
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    from server.runtime.kernel import Kernel

log = logging.getLogger("motiond.jobs")
MAX_NAME = 200
UPLOAD_PREFIX = ".upload-"
# Control characters (C0, DEL, C1) and every line break str.splitlines knows.
_BAD_NAME_CHARACTER = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")
YIELD_AFTER_S = 0.0003  # the job feeder gives other tasks a turn at least this often


@dataclass(slots=True)
class JobFile:
    name: str
    size_bytes: int
    modified_s: float


@dataclass(slots=True)
class JobProgress:
    """The current or last job. ``state``: running, paused, done, aborted or failed."""

    name: str
    state: str
    lines_total: int = 0
    lines_done: int = 0
    percent: float = 0.0
    elapsed_s: float = 0.0
    remaining_s: float | None = None
    error: str | None = None
    estimate_s: float | None = None
    started_s: float = 0.0


@dataclass(slots=True)
class _JobSource:
    name: str
    can_control: bool = True


class Jobs:
    """The job files of one kernel and the one job that may play at a time."""

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.jobs_dir = jobs_dir(kernel.config.core)
        self.max_bytes = kernel.config.core.jobs.max_upload_bytes
        remove_stale_uploads(self.jobs_dir)
        self._task: asyncio.Task[None] | None = None
        self._progress: JobProgress | None = None
        dispatcher = kernel.dispatcher
        dispatcher.register("ls", self._ls, when_locked=True, query=True)
        dispatcher.register("play", self._play)
        dispatcher.register_immediate("progress", self._status, query=True)
        for name, handler in (("abort", self._abort), ("suspend", self._suspend),
                              ("resume", self._resume)):
            dispatcher.register_immediate(name, handler)  # a held job holds the stream

    # -- files ------------------------------------------------------------------------------
    def path(self, name: str) -> Path:
        """The file for ``name``, refusing anything that could leave the data directory or
        break a line of the protocol."""
        if _BAD_NAME_CHARACTER.search(name):
            raise CommandError(
                Error.FILE_ERROR,
                f"invalid job file name {name!r}: control characters or line breaks",
            )
        name = name.strip().removeprefix("/sd/")
        bad = (
            not name
            or len(name) > MAX_NAME
            or name.startswith(".")
            or "\0" in name
            or "/" in name
            or "\\" in name
            or name in ("..", ".")
        )
        if bad:
            raise CommandError(Error.FILE_ERROR, f"invalid job file name {name!r}")
        path = (self.jobs_dir / name).resolve()
        if path.parent != self.jobs_dir.resolve():
            raise CommandError(Error.FILE_ERROR, f"invalid job file name {name!r}")
        return path

    def files(self) -> list[JobFile]:
        """Stored job files, by name."""
        if not self.jobs_dir.is_dir():
            return []
        files = []
        for entry in os.scandir(self.jobs_dir):
            if entry.is_file() and valid_name(entry.name):
                info = entry.stat()
                files.append(JobFile(entry.name, info.st_size, info.st_mtime))
        return sorted(files, key=lambda f: f.name)

    async def save(self, name: str, data: bytes) -> JobFile:
        async def one_chunk() -> AsyncIterator[bytes]:
            yield data

        return await self.save_stream(name, one_chunk(), self.max_bytes)

    async def save_stream(
        self, name: str, chunks: AsyncIterator[bytes], limit_bytes: int
    ) -> JobFile:
        """Write a file atomically (temp file, then rename); nothing is left behind on error."""
        path = self.path(name)
        await asyncio.to_thread(self.jobs_dir.mkdir, parents=True, exist_ok=True)
        handle, temp = await asyncio.to_thread(_temp_file, self.jobs_dir)
        size = 0
        try:
            async for chunk in chunks:
                size += len(chunk)
                if size > limit_bytes:
                    raise CommandError(Error.FILE_ERROR, f"upload larger than {limit_bytes} bytes")
                await asyncio.to_thread(handle.write, chunk)
            await asyncio.to_thread(_finish_file, handle, temp, path)
        except OSError as exc:
            raise CommandError(Error.FILE_ERROR, f"cannot store {name}: {exc.strerror}") from exc
        finally:
            handle.close()
            with contextlib.suppress(FileNotFoundError):
                temp.unlink()
        return JobFile(path.name, size, time.time())

    async def delete(self, name: str) -> None:
        path = self.path(name)
        try:
            await asyncio.to_thread(path.unlink)
        except OSError as exc:
            raise CommandError(Error.FILE_ERROR, f"cannot delete {name}: {exc.strerror}") from exc

    # -- playing ----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    def is_playing(self) -> bool:
        """A job is streaming (not paused)."""
        return self.running and self._progress is not None and self._progress.state == "running"

    def is_paused(self) -> bool:
        return self._progress is not None and self._progress.state == "paused"

    @property
    def active(self) -> bool:
        """A job is running or paused (not yet done, failed or aborted)."""
        progress = self._progress
        return progress is not None and progress.state in ("running", "paused")

    def play(self, name: str) -> None:
        """Start playing a stored file."""
        if self.running:
            raise CommandError(Error.BUSY, "a job is already running; abort it first")
        if self.kernel.state not in (MachineState.IDLE, MachineState.RUN):
            raise CommandError(Error.BUSY, f"cannot start a job in state {self.kernel.state.value}")
        path = self.path(name)
        if not path.is_file():
            raise CommandError(Error.FILE_ERROR, f"no job file {path.name}")
        self._progress = JobProgress(path.name, "running", started_s=self.kernel.clock.now_s())
        source = _JobSource(f"job:{path.name}")
        self.kernel.dispatcher.claim(source)  # other connections may query, hold and stop
        self._task = asyncio.get_running_loop().create_task(
            self._run(path, self._progress, source), name=f"job:{path.name}"
        )
        self._announce()

    def abort(self) -> None:
        """Stop the job and all motion at once; tools off."""
        progress = self._progress
        if progress is not None and progress.state in ("running", "paused"):
            progress.state = "aborted"
        self.kernel.machine.stop_now()
        self.kernel.events.emit(Event.HALT, "job aborted")
        if self.kernel.state in (MachineState.RUN, MachineState.HOLD):
            self.kernel.set_state(MachineState.IDLE)
        if self._task is not None:
            self._task.cancel()
        self._announce()

    def suspend(self) -> None:
        if self.running and self._progress is not None:
            self.kernel.machine.feed_hold()
            self._progress.state = "paused"
            self._announce()

    def resume(self) -> None:
        if self._progress is not None and self._progress.state == "paused":
            self.kernel.machine.cycle_start()
            self._progress.state = "running"
            self._announce()

    def progress(self) -> JobProgress | None:
        """The current or last job, with times brought up to date."""
        progress = self._progress
        if progress is not None and progress.state in ("running", "paused"):
            progress.elapsed_s = self.kernel.clock.now_s() - progress.started_s
            if progress.estimate_s is not None:
                progress.remaining_s = max(0.0, progress.estimate_s - progress.elapsed_s)
        return progress

    async def close(self) -> None:
        """Stop the player task (shutdown)."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def _run(self, path: Path, progress: JobProgress, source: _JobSource) -> None:
        try:
            core = self.kernel.config.core
            lines = await asyncio.to_thread(read_file_lines, path, core.protocol.line_limit)
            progress.lines_total = len(lines)
            interpreter = self.kernel.machine.new_interpreter()
            stats = await asyncio.to_thread(
                estimate, lines, core.model_copy(deep=True), None, interpreter
            )
            progress.estimate_s = stats.duration_s
            await self._stream(lines, progress, source)
        except OSError as exc:
            self._fail(progress, f"cannot read {path.name}: {exc.strerror}")

    async def _stream(self, lines: list[str], progress: JobProgress, source: _JobSource) -> None:
        dispatcher, machine = self.kernel.dispatcher, self.kernel.machine
        loop = asyncio.get_running_loop()
        turn_s = loop.time()
        limit = self.kernel.config.core.protocol.line_limit
        pending: deque[tuple[int, asyncio.Future[list[str]]]] = deque()
        for number, line in enumerate(lines, 1):
            try:
                check_length(line, limit)  # error 11, as a stream refuses it
                await dispatcher.submit(line, source, defer=_deferring(pending, number))
                await _settle(pending, wait=False)
            except _LineFailed as failed:
                self._fail(progress, failed.text)
                return
            except CommandError as exc:
                self._fail(progress, f"line {number}: error:{exc.code} {exc.message}")
                return
            progress.lines_done = number
            progress.percent = 100.0 * number / max(1, len(lines))
            if loop.time() - turn_s > YIELD_AFTER_S:  # lines that never wait must not hog
                await asyncio.sleep(0)
                turn_s = loop.time()
        try:
            await _settle(pending, wait=True)
        except _LineFailed as failed:
            self._fail(progress, failed.text)
            return
        await machine.wait_idle()
        if self.kernel.state is MachineState.ALARM:
            self._fail(progress, f"line {progress.lines_done}: stopped by an alarm")
            return
        progress.state, progress.percent = "done", 100.0
        progress.remaining_s = 0.0
        self.progress()
        self.kernel.push(f"[MSG:job {progress.name} done in {format_duration(progress.elapsed_s)}]")
        self._announce()

    def _fail(self, progress: JobProgress, message: str) -> None:
        progress.state, progress.error = "failed", message
        log.warning("job %s stopped at %s", progress.name, message)
        self.kernel.push(f"[MSG:job {progress.name} stopped at {message}]")
        self._announce()

    def _announce(self) -> None:
        self.kernel.events.emit(Event.JOB, self.progress())

    # -- Smoothie commands ------------------------------------------------------------------
    def _ls(self, command: Command) -> list[str]:
        sizes = "-s" in command.args
        return [
            f"{'./' if f.name.lower().startswith('ok') else ''}{f.name}"
            + (f" {f.size_bytes}" if sizes else "")
            for f in self.files()
        ]

    def _play(self, command: Command) -> list[str]:
        name = command.args.split()[0] if command.args.split() else ""
        self.play(name)
        return [f"[MSG:Playing {self.path(name).name}]"]

    def _status(self, command: Command) -> list[str]:
        progress = self.progress()
        if progress is None or progress.state not in ("running", "paused"):
            return ["[MSG:Not currently playing]"]
        remaining = progress.remaining_s
        return [
            f"[MSG:file: {progress.name}, {progress.percent:.0f} % complete, elapsed time: "
            f"{_clock(progress.elapsed_s)}, est time: "
            f"{'-' if remaining is None else _clock(remaining)}]"
        ]

    def _abort(self, command: Command) -> list[str]:
        self.abort()
        return ["[MSG:Aborted playing or paused file]"]

    def _suspend(self, command: Command) -> None:
        self.suspend()

    def _resume(self, command: Command) -> None:
        self.resume()


def _deferring(
    pending: deque[tuple[int, asyncio.Future[list[str]]]], number: int
) -> Callable[[asyncio.Future[list[str]]], None]:
    """The ``defer`` of line ``number``: its answer-to-come joins ``pending``."""
    return lambda future: pending.append((number, future))


class _LineFailed(Exception):
    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text


async def _settle(pending: deque[tuple[int, asyncio.Future[list[str]]]], *, wait: bool) -> None:
    """Drop the deferred answers that came (all of them, waiting, with ``wait``); raise
    :class:`_LineFailed` naming the first line the controller refused."""
    while pending and (wait or pending[0][1].done()):
        number, future = pending[0]
        try:
            await future
        except CommandError as exc:
            raise _LineFailed(f"line {number}: error:{exc.code} {exc.message}") from exc
        pending.popleft()


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}"


def valid_name(name: str) -> bool:
    """Whether a file in the data directory may be listed and played under ``name``."""
    return not name.startswith(".") and len(name) <= MAX_NAME and not (
        _BAD_NAME_CHARACTER.search(name) or "\\" in name or name != name.strip())


def remove_stale_uploads(folder: Path) -> None:
    """Remove ``.upload-*`` files a crash left in the data directory (start-up, one server per
    data directory)."""
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        return
    except OSError as exc:
        log.warning("cannot look for stale uploads in %s: %s", folder, exc.strerror)
        return
    for entry in entries:
        if entry.name.startswith(UPLOAD_PREFIX) and entry.is_file(follow_symlinks=False):
            try:
                os.unlink(entry.path)
                log.info("removed %s, left by an interrupted upload", entry.name)
            except OSError as exc:
                log.warning("cannot remove %s: %s", entry.path, exc.strerror)


def _temp_file(folder: Path) -> tuple[BinaryIO, Path]:
    descriptor, name = tempfile.mkstemp(dir=folder, prefix=UPLOAD_PREFIX)
    return os.fdopen(descriptor, "wb"), Path(name)


def _finish_file(handle: BinaryIO, temp: Path, path: Path) -> None:
    handle.flush()
    os.fsync(handle.fileno())
    handle.close()
    os.replace(temp, path)
