"""Serial transports: a real device (pyserial-asyncio) and a pseudo-terminal motiond creates.

``--pty PATH`` creates a pseudo-terminal in raw mode and links its device at PATH (as Klipper
does with /tmp/printer), so serial-only senders connect to it like a USB port. While no client
has the terminal open, the master side reads EIO; the transport then polls until a client opens
it, greets it with the banner, serves it, and goes back to waiting when it closes — so the same
PATH can be opened again and again.

The terminal device gets ``[serial] pty_mode`` (0o660) and ``pty_group`` (``dialout``, as a
USB serial port), so a host running as another user in that group can open it. Linux follows a
symbolic link in a sticky world-writable folder (``/tmp``) only for the link's owner
(``fs.protected_symlinks``): for such a host, put the link elsewhere (``/run/motiond/tty``).

motiond only ever replaces its own link: if PATH exists and is anything but a symbolic link to
a pseudo-terminal device (``/dev/pts/N``) owned by this user — a stale link from an earlier
run — it refuses to start rather than delete someone's file. It removes the link on close only
if the link still points to its own terminal.

Input is read in slices and fed to the session like TCP's (see :mod:`server.transports.tcp`):
reading pauses only while the session's backlog is full.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import grp
import logging
import os
import re
import termios
import tty
from collections.abc import Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

from server.errors import ConfigError
from server.sessions.session import Session, login_guard

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

log = logging.getLogger("motiond.serial")
POLL_S = 0.05
READ_CHUNK = 4096
_PTY_DEVICE = re.compile(r"/dev/(?:pts/\d+|ttys\d+)")  # Linux, macOS


class SerialTransport:
    """Serves ``[serial] device`` and/or ``[serial] pty``."""

    name = "serial"

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.config = kernel.config.core.serial
        self._tasks: set[asyncio.Task[None]] = set()
        self.pty: PtyPort | None = None
        if self.config.pty:
            stale_pty_link(Path(self.config.pty))  # refuse to start before anything runs

    async def start(self) -> None:
        if self.config.pty:
            self.pty = PtyPort(self.kernel, Path(self.config.pty))
            self._spawn(self.pty.serve())
        if self.config.device:
            self._spawn(self._serve_device(self.config.device))

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def close(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.pty is not None:
            self.pty.close()

    async def _serve_device(self, device: str) -> None:
        import serial_asyncio_fast as serial_asyncio  # pyserial-asyncio-fast

        from server.transports.tcp import serve_stream

        while True:
            try:
                reader, writer = await serial_asyncio.open_serial_connection(
                    url=device, baudrate=self.config.baud
                )
            except (OSError, ValueError) as exc:
                log.warning("cannot open %s (%s); retrying", device, exc)
                await asyncio.sleep(1.0)
                continue
            log.info("serving serial device %s at %d baud", device, self.config.baud)
            await serve_stream(Session(self.kernel, f"serial:{device}"), reader, writer)
            await asyncio.sleep(0.2)


class PtyPort:
    """A pseudo-terminal linked at ``link``; see the module docstring."""

    def __init__(self, kernel: Kernel, link: Path) -> None:
        self.kernel = kernel
        self.link = link
        if stale_pty_link(link):
            link.unlink()
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.device = os.ttyname(slave)
        os.close(slave)
        config = kernel.config.core.serial
        share_device(self.device, config.pty_mode, config.pty_group)
        os.set_blocking(self.master, False)
        try:
            self.link.symlink_to(self.device)
        except OSError as exc:
            os.close(self.master)
            raise ConfigError([f"[serial] pty: cannot create {link}: {exc.strerror}"]) from exc
        self.sessions = 0
        self._guard = login_guard(kernel)
        log.info("pseudo-terminal %s linked at %s", self.device, self.link)

    async def serve(self) -> None:
        """Wait for a client, serve it until it closes the terminal, repeat."""
        while True:
            first = await self._wait_for_client()
            self.sessions += 1
            session = Session(self.kernel, f"pty-{self.sessions}", peer=f"pty {self.link}",
                              guard=self._guard)
            await self._serve(session, first)

    async def _wait_for_client(self) -> bytes:
        while True:
            try:
                return os.read(self.master, READ_CHUNK)
            except BlockingIOError:
                return b""
            except OSError as exc:
                if exc.errno != errno.EIO:
                    raise
            await asyncio.sleep(POLL_S)

    async def _serve(self, session: Session, first: bytes) -> None:
        loop = asyncio.get_running_loop()
        readable = asyncio.Event()
        session.start()
        writer = loop.create_task(self._write_loop(session, readable))
        loop.add_reader(self.master, readable.set)
        try:
            if first:
                await session.feed(first)
            while not session.closed:
                await readable.wait()
                readable.clear()
                data = self._read()
                if data is None:
                    break
                # stop watching while the session paces or its backlog is full
                loop.remove_reader(self.master)
                await session.feed(data)
                loop.add_reader(self.master, readable.set)
                await asyncio.sleep(0)  # one slice a turn
        finally:
            loop.remove_reader(self.master)
            with contextlib.suppress(termios.error):
                termios.tcflush(self.master, termios.TCIOFLUSH)  # nothing stale for the next client
            await session.close()
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer

    def _read(self) -> bytes | None:
        try:
            return os.read(self.master, READ_CHUNK)
        except BlockingIOError:
            return b""
        except OSError:  # EIO: the client closed the terminal
            return None

    async def _write_loop(self, session: Session, readable: asyncio.Event) -> None:
        while True:
            data = await session.outbox.get()
            if data is None:
                readable.set()  # the session ended: wake the reader so it sees that
                return
            while data:
                try:
                    written = os.write(self.master, data)
                except BlockingIOError:
                    if session.outbox.closed:
                        return
                    await asyncio.sleep(0.005)
                    continue
                except OSError:
                    return
                data = data[written:]

    def close(self) -> None:
        """Remove the link if it is still ours; close the terminal. Repeatable."""
        self._guard.close()
        with contextlib.suppress(OSError):
            if os.readlink(self.link) == self.device:
                self.link.unlink()
        with contextlib.suppress(OSError):
            os.close(self.master)


def share_device(device: str, mode: int, group: str) -> None:
    """Give the terminal ``device`` its permissions and group (see the module docstring).

    An empty group leaves it as created; a group that does not exist here, or that this user
    may not give, is logged and skipped: the terminal then keeps the group it had."""
    os.chmod(device, mode)
    if not group:
        return
    try:
        gid = grp.getgrnam(group).gr_gid
    except KeyError:
        log.warning("[serial] pty_group: no group %r here; %s keeps its group", group, device)
        return
    try:
        os.chown(device, -1, gid)
    except PermissionError:
        log.warning("[serial] pty_group: may not give %s to group %r", device, group)


def stale_pty_link(link: Path) -> bool:
    """Whether ``link`` is a link to a pseudo-terminal left by an earlier run (to replace);
    False if nothing is there.

    Raises:
        ConfigError: something else is at ``link``: it must not be deleted.
    """
    try:
        info = link.lstat()
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise ConfigError([f"[serial] pty: cannot check {link}: {exc.strerror}"]) from exc
    if (
        link.is_symlink()
        and info.st_uid == os.getuid()
        and _PTY_DEVICE.fullmatch(os.readlink(link)) is not None
    ):
        return True
    raise ConfigError([
        f"[serial] pty: {link} exists and is not a link to a pseudo-terminal left by "
        "motiond; refusing to replace it (remove it or choose another --pty path)"
    ])
