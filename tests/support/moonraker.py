"""The real Moonraker (PyPI ``moonraker`` 0.11.0) in front of a motiond's ``[klippy_api]``.

Moonraker pins its own dependencies, so it lives in a virtual environment of its own under the
repository's ignored ``build/`` folder (:mod:`tests.support.moonraker_venv`: ``.ci/run``
builds it at install time, the fixture when absent). Each test runs it with a
data folder in ``tmp_path``, ``HOME`` there too, its announcements off, no update manager and
no system service provider: nothing leaves this machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp

from tests.support.moonraker_venv import ensure_moonraker
from tests.support.processes import free_port, stop_process


def moonraker_conf(port: int, socket: Path) -> str:
    return f"""\
[server]
host: 127.0.0.1
port: {port}
klippy_uds_address: {socket}

[authorization]
trusted_clients:
    127.0.0.0/8
cors_domains:
    *

[machine]
provider: none
validate_service: False
validate_config: False

[announcements]
enable_moonlight: False

[history]
"""


@dataclass
class Moonraker:
    url: str
    port: int
    data_dir: Path
    session: aiohttp.ClientSession
    log_path: Path

    async def get(self, path: str, **params: str) -> Any:
        async with self.session.get(self.url + path, params=params) as response:
            body = await response.json()
            if response.status != 200:
                raise AssertionError(f"GET {path}: {response.status} {body}")
            return body["result"]

    async def post(self, path: str, payload: dict[str, Any] | None = None) -> Any:
        async with self.session.post(self.url + path, json=payload or {}) as response:
            body = await response.json()
            if response.status != 200:
                raise MoonrakerError(response.status, body)
            return body["result"]

    async def gcode(self, script: str) -> Any:
        return await self.post("/printer/gcode/script", {"script": script})

    async def query(self, **objects: list[str] | None) -> dict[str, Any]:
        params = {name: ",".join(fields) if fields else "" for name, fields in objects.items()}
        result = await self.get("/printer/objects/query", **params)
        return dict(result["status"])

    async def wait_for(self, check: Any, timeout_s: float = 20.0, **objects: Any) -> Any:
        """Query ``objects`` until ``check(status)`` is true; the last status."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while True:
            status = await self.query(**objects)
            if check(status):
                return status
            if asyncio.get_running_loop().time() > deadline:
                raise AssertionError(f"timed out; last status {json.dumps(status)[:2000]}")
            await asyncio.sleep(0.1)


class MoonrakerError(AssertionError):
    def __init__(self, status: int, body: Any) -> None:
        super().__init__(f"{status}: {body}")
        self.status, self.body = status, body


DOC = Path(__file__).resolve().parents[2] / "docs" / "moonraker.md"


def documented_config(home: Path) -> tuple[str, str, list[str]]:
    """docs/moonraker.md's configuration, verbatim: motiond's TOML, ``moonraker.conf`` (with
    ``{port}`` for the port, so that tests on one host do not collide) and the options of
    motiond's ``ExecStart`` but ``--config`` (``/home/laser`` is ``home``)."""
    text = DOC.read_text()
    toml = text.split("```toml\n", 1)[1].split("```", 1)[0]
    conf = text.split("```ini\n", 1)[1].split("```", 1)[0]
    assert "port: 7125\n" in conf, "moonraker.md: Moonraker's port is no longer 7125"
    command = re.search(r"ExecStart=\S+/motiond (.*)", text)
    assert command is not None, "moonraker.md: no ExecStart for motiond"
    words = command.group(1).replace("/home/laser", str(home)).split()
    options = [word for pair in zip(words[::2], words[1::2], strict=True)
               if pair[0] != "--config" for word in pair]
    return toml, conf.replace("port: 7125\n", "port: {port}\n"), options


@contextlib.asynccontextmanager
async def moonraker(tmp_path: Path, socket: Path, gcodes: Path | None = None, *,
                    conf: str | None = None, home: Path | None = None,
                    ) -> AsyncIterator[Moonraker]:
    """Moonraker on a free port, for the motiond API socket ``socket``, until Klippy is ready.
    Either with ``gcodes`` (motiond's jobs folder, linked in as its own) and the tests'
    configuration, or as the user whose ``home`` holds ``~/printer_data`` with ``conf``."""
    program = await asyncio.to_thread(ensure_moonraker)
    if home is None:
        home = tmp_path / "home"
        data = tmp_path / "printer_data"
    else:
        data = home / "printer_data"
    (data / "config").mkdir(parents=True, exist_ok=True)
    if gcodes is not None:
        (data / "gcodes").symlink_to(gcodes, target_is_directory=True)
    home.mkdir(exist_ok=True)
    port = free_port()
    text = conf.replace("{port}", str(port)) if conf else moonraker_conf(port, socket)
    (data / "config" / "moonraker.conf").write_text(text)
    log_path = tmp_path / "moonraker.log"
    with log_path.open("ab") as log:
        process = await asyncio.create_subprocess_exec(
            str(program), "-d", str(data), "-n",
            env={**os.environ, "HOME": str(home)}, stdout=log, stderr=log)
    try:
        async with aiohttp.ClientSession() as session:
            server = Moonraker(f"http://127.0.0.1:{port}", port, data, session, log_path)
            await _wait_ready(server, process)
            yield server
    finally:
        await stop_process(process)


async def _wait_ready(server: Moonraker, process: asyncio.subprocess.Process) -> None:
    for _ in range(600):
        if process.returncode is not None:
            raise RuntimeError(f"moonraker exited: {server.log_path.read_text()[-3000:]}")
        with contextlib.suppress(aiohttp.ClientError, AssertionError):
            info = await server.get("/server/info")
            if info.get("klippy_state") == "ready":
                return
        await asyncio.sleep(0.1)
    raise TimeoutError(f"moonraker not ready: {server.log_path.read_text()[-3000:]}")
