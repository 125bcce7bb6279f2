"""The job files: a flat folder of G-code files, written atomically, named safely.

Files live flat in the data folder's ``jobs/`` (:func:`server.paths.jobs_dir`). A name is a
plain file name: no folders, no ``..``, no leading dot, no control character and nothing
``str.splitlines`` splits on (a name is sent inside reply and pushed lines: ``\n``, ``\r``,
U+2028... would break them into several lines, a bare ``ok`` among them); Smoothie's ``/sd/``
prefix is accepted and dropped. A file on disk whose name breaks these rules is never listed.
Uploads are written to a hidden ``.upload-*`` file and renamed; such files left by a crash are
removed at start-up. File I/O runs in a thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import tempfile
import time
import unicodedata
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from server.errors import CommandError, Error

log = logging.getLogger("motiond.jobs")
MAX_NAME = 200
UPLOAD_PREFIX = ".upload-"
# Control characters (C0, DEL, C1) and every line break str.splitlines knows.
_BAD_NAME_CHARACTER = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")
# Unicode categories no file name needs: controls, format characters (the bidi overrides that
# show "\u202egnp.nc" as "cn.png", zero-width characters), separators, surrogates, unassigned
_BAD_CATEGORIES = frozenset({"Cc", "Cf", "Zl", "Zp", "Cs", "Co", "Cn"})
_IDEOGRAPHIC_STOPS = frozenset("\u3002\uff61")
# Names Windows gives to devices, whatever the extension (a job copied to a share or a PC)
_DEVICE = re.compile(r"(?:CON|PRN|AUX|NUL|COM[0-9\u00b9\u00b2\u00b3]|LPT[0-9\u00b9\u00b2\u00b3]"
                     r"|CONIN\$|CONOUT\$)(?:\..*)?", re.IGNORECASE)

@dataclass(slots=True)
class JobFile:
    name: str
    size_bytes: int
    modified_s: float


class JobStore:
    """The job files of one server (:class:`~server.jobs.jobs.Jobs` plays them)."""

    def __init__(self, jobs_dir: Path, max_bytes: int) -> None:
        self.jobs_dir, self.max_bytes = jobs_dir, max_bytes
        remove_stale_uploads(jobs_dir)

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
        problem = name_problem(name)
        if problem is not None:
            raise CommandError(Error.FILE_ERROR, f"invalid job file name {name!r}: {problem}")
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


def valid_name(name: str) -> bool:
    """Whether a file in the data directory may be listed and played under ``name``."""
    return not name.startswith(".") and len(name) <= MAX_NAME and not (
        _BAD_NAME_CHARACTER.search(name) or "\\" in name or name != name.strip()
        or name_problem(name))


def name_problem(name: str) -> str | None:
    """Why ``name`` misleads or fails elsewhere, or None: a character that is not what it
    looks like (a bidi override, a zero-width or look-alike dot), a Windows device name
    (``CON``, ``NUL.nc``), or a trailing dot (Windows drops it)."""
    for char in name:
        category = unicodedata.category(char)
        if category in _BAD_CATEGORIES:
            return f"invisible or control character U+{ord(char):04X} ({category})"
        if char != "." and ("." in unicodedata.normalize("NFKC", char)
                            or char in _IDEOGRAPHIC_STOPS):
            return f"U+{ord(char):04X} looks like a dot but is not one"
    if _DEVICE.fullmatch(name.rstrip(" .")):
        return "a device name on Windows"
    if name.endswith("."):
        return "ends with a dot"
    return None


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
