"""A client of Klipper's API socket (``[klippy_api]``), as Moonraker speaks it, and a reader
of a process' resident memory.

:class:`KlippyClient` writes requests (``{"id", "method", "params"}`` ended by ``\\x03``) and
sorts what comes back into answers by id and pushed messages; :meth:`KlippyClient.raw` sends
bytes as they are, for hostile requests. :func:`rss_mib` reads ``VmRSS`` from
``/proc/<pid>/status``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

ETX = b"\x03"
ALL_OBJECTS = {name: None for name in (
    "webhooks", "configfile", "gcode", "toolhead", "gcode_move", "motion_report",
    "print_stats", "virtual_sdcard", "pause_resume", "display_status", "idle_timeout",
    "system_stats")}


class KlippyClient:
    """One connection to the API socket; ids count up from 1."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.pushed: list[dict[str, Any]] = []
        self.answers: dict[Any, dict[str, Any]] = {}
        self._next_id = 0

    def request(self, method: str, **params: Any) -> bytes:
        """The next request's bytes (its id taken), for pipelining many in one write."""
        self._next_id += 1
        return json.dumps({"id": self._next_id, "method": method, "params": params}
                          ).encode() + ETX

    async def send(self, method: str, **params: Any) -> int:
        await self.raw(self.request(method, **params))
        return self._next_id

    async def raw(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def message(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """The next message, whatever it is (EOF: ConnectionError)."""
        data = await asyncio.wait_for(self.reader.readuntil(ETX), timeout_s)
        message: dict[str, Any] = json.loads(data[:-1])
        return message

    async def answer(self, request_id: Any, timeout_s: float = 10.0) -> dict[str, Any]:
        """The answer to ``request_id``, keeping what comes before it."""
        async with asyncio.timeout(timeout_s):
            while request_id not in self.answers:
                message = await self.message(timeout_s)
                if "id" in message:
                    self.answers[message["id"]] = message
                else:
                    self.pushed.append(message)
        return self.answers.pop(request_id)

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        return await self.answer(await self.send(method, **params))

    async def closed_by_server(self, timeout_s: float = 5.0) -> bool:
        """Whether the server closes the connection within ``timeout_s`` (answers meanwhile
        are kept)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                while True:
                    try:
                        message = await self.message(timeout_s)
                    except (asyncio.IncompleteReadError, ConnectionError):
                        return True
                    if "id" in message:
                        self.answers[message["id"]] = message
        return False

    def close(self) -> None:
        self.writer.close()

    async def pipeline(self, count: int, method: str, **params: Any) -> list[dict[str, Any]]:
        """``count`` requests in one write, then their answers in order."""
        first_id = self._next_id + 1
        await self.raw(b"".join(self.request(method, **params) for _ in range(count)))
        return [await self.answer(first_id + index) for index in range(count)]


@contextlib.asynccontextmanager
async def klippy_client(socket: Path) -> AsyncIterator[KlippyClient]:
    reader, writer = await asyncio.open_unix_connection(str(socket), limit=4 << 20)
    try:
        yield KlippyClient(reader, writer)
    finally:
        writer.close()


def rss_mib(pid: int) -> float:
    """The resident memory of process ``pid`` in MiB (``VmRSS``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for process {pid}")
