"""OctoPrint (PyPI) as a real host for the e2e suite: its own virtual environment, every online
feature off, driven through its REST API.

The environment is built once into ``build/octoprint-<version>/`` (ignored by git; ``.ci/run``
builds it before the tests). :class:`OctoPrint` runs ``octoprint serve`` on a fresh base folder
whose config turns off everything that reaches the network (online check, plugin blacklist,
software update, announcements, tracking, error tracking, discovery, plugin repository), logs
the serial line and OctoPrint's communication layer at debug level, and lets one user in by API
key. It runs as root here, which OctoPrint refuses without ``--iknowwhatimdoing``.
"""

from __future__ import annotations

import asyncio
import http.client
import os
import secrets
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import aiohttp

from tests.conftest import REPO
from tests.support.processes import free_port

VERSION = "1.11.8"
VENV = REPO / "build" / f"octoprint-{VERSION}"
EXECUTABLE = VENV / "bin" / "octoprint"
OFFLINE_PLUGINS = ["announcements", "softwareupdate", "tracking", "errortracking", "discovery",
                   "pluginmanager", "backup", "achievements", "health_check", "virtual_printer",
                   "gcodeviewer", "firmware_check", "file_check", "pi_support"]
# config.yaml's custom control for a machine in alarm, as docs/octoprint.md gives it: a button
# "Unlock" on the Control tab that sends M999 (Marlin's "restart after stop", motiond's $X)
UNLOCK_CONTROL = [{"name": "motiond", "layout": "horizontal",
                   "children": [{"name": "Unlock", "command": "M999"}]}]


def ensure_venv() -> Path:
    """The ``octoprint`` executable, building its environment first if it is missing."""
    if not EXECUTABLE.exists():
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        subprocess.run([str(VENV / "bin" / "pip"), "install", "-q", f"OctoPrint=={VERSION}"],
                       check=True)
    return EXECUTABLE


class OctoPrint:
    """One ``octoprint serve`` process on ``basedir``; see the module docstring.

    Args:
        basedir: an empty folder for its config, logs and uploads.
        port_path: the serial port it may connect to (motiond's pty link).
        timeouts_s: ``serial.timeout`` values to set (``communication``...).
        scripts: G-code scripts by name (``afterPrintCancelled``...).
    """

    def __init__(self, basedir: Path, port_path: Path, *, timeouts_s: dict[str, float],
                 scripts: dict[str, str]) -> None:
        self.basedir = basedir
        self.port_path = port_path
        self.port = free_port()
        self.api_key = secrets.token_hex(16)
        self.url = f"http://127.0.0.1:{self.port}"
        self._write_config(timeouts_s, scripts)
        self._process: subprocess.Popen[bytes] | None = None

    def _write_config(self, timeouts_s: dict[str, float], scripts: dict[str, str]) -> None:
        import json  # YAML is a superset of JSON: no YAML writer needed

        self.basedir.mkdir(parents=True, exist_ok=True)
        config = {
            "server": {"firstRun": False, "onlineCheck": {"enabled": False},
                       "pluginBlacklist": {"enabled": False},
                       "seenWizards": {"corewizard": 4}},
            "serial": {"additionalPorts": [str(self.port_path)], "log": True,
                       "timeout": timeouts_s, "autoconnect": False},
            "plugins": {"_disabled": OFFLINE_PLUGINS},
            "feature": {"sdSupport": True},
            "controls": UNLOCK_CONTROL,  # docs/octoprint.md's "Unlock" button
            # the web UI in a test's browser on this machine is this user, without a login
            "accessControl": {"autologinLocal": True, "autologinAs": "motiond",
                              "autologinHeadsupAcknowledged": True},
        }
        (self.basedir / "config.yaml").write_text(json.dumps(config))
        users = {"motiond": {"active": True, "apikey": self.api_key, "groups": ["admins", "users"],
                             "password": "-", "permissions": [], "settings": {}}}
        (self.basedir / "users.yaml").write_text(json.dumps(users))
        logging = {"loggers": {"octoprint.util.comm": {"level": "DEBUG"},
                               "octoprint.events": {"level": "DEBUG"}}}
        (self.basedir / "logging.yaml").write_text(json.dumps(logging))
        folder = self.basedir / "scripts" / "gcode"
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in scripts.items():
            (folder / name).write_text(text)

    def start(self, timeout_s: float = 120.0) -> None:
        """Start the server and wait until its API answers (it takes 10-30 s here); a port
        taken by another program meanwhile (OctoPrint exits) is replaced once."""
        executable = ensure_venv()
        for _attempt in range(2):
            if self._launch(executable, timeout_s):
                return
            self.port = free_port()
            self.url = f"http://127.0.0.1:{self.port}"
        raise AssertionError(f"OctoPrint did not start: {self.log()[-2000:]}")

    def _launch(self, executable: Path, timeout_s: float) -> bool:
        """Run the server; True once its API answers, False if it exited."""
        self._process = subprocess.Popen(
            [str(executable), "serve", "--iknowwhatimdoing", "--basedir", str(self.basedir),
             "--host", "127.0.0.1", "--port", str(self.port)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env={**os.environ, "HOME": str(self.basedir)})
        deadline = time.monotonic() + timeout_s
        request = urllib.request.Request(self.url + "/api/version",
                                         headers={"X-Api-Key": self.api_key})
        while self._process.poll() is None:
            try:
                with urllib.request.urlopen(request, timeout=5) as reply:
                    if reply.status == 200:
                        return True
            except (OSError, http.client.HTTPException):
                pass  # not listening yet
            if time.monotonic() > deadline:
                raise AssertionError(f"OctoPrint did not answer: {self.log()[-2000:]}")
            time.sleep(0.5)
        return False

    def close(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(15)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()

    def api(self) -> Api:
        """A REST client (use ``async with``) in the running event loop."""
        return Api(self)

    # -- logs --------------------------------------------------------------------------------
    def serial_log(self) -> str:
        return _read(self.basedir / "logs" / "serial.log")

    def log(self) -> str:
        return _read(self.basedir / "logs" / "octoprint.log")


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


class Api:
    """OctoPrint's REST API, authenticated by the user's API key."""

    def __init__(self, server: OctoPrint) -> None:
        self.server = server
        self._http = aiohttp.ClientSession(headers={"X-Api-Key": server.api_key})

    async def __aenter__(self) -> Api:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self._http.close()

    async def get(self, path: str) -> Any:
        async with self._http.get(self.server.url + path) as reply:
            assert reply.status == 200, (path, reply.status, await reply.text())
            return await reply.json()

    async def post(self, path: str, body: dict[str, Any]) -> None:
        async with self._http.post(self.server.url + path, json=body) as reply:
            assert reply.status in (200, 201, 204), (path, reply.status, await reply.text())

    async def upload(self, name: str, text: str) -> None:
        form = aiohttp.FormData()
        form.add_field("file", text.encode(), filename=name, content_type="text/x.gcode")
        async with self._http.post(self.server.url + "/api/files/local", data=form) as reply:
            assert reply.status == 201, (reply.status, await reply.text())

    async def connect(self) -> None:
        await self.post("/api/connection", {"command": "connect", "baudrate": 115200,
                                            "port": str(self.server.port_path)})

    async def disconnect(self) -> None:
        await self.post("/api/connection", {"command": "disconnect"})

    async def state(self) -> str:
        return str((await self.get("/api/connection"))["current"]["state"])

    async def job(self) -> dict[str, Any]:
        result: dict[str, Any] = await self.get("/api/job")
        return result

    async def terminal(self, *commands: str) -> None:
        await self.post("/api/printer/command", {"commands": list(commands)})

    async def print_file(self, name: str) -> None:
        await self.post(f"/api/files/local/{name}", {"command": "select", "print": True})

    async def job_command(self, command: str, action: str | None = None) -> None:
        body = {"command": command} if action is None else {"command": command, "action": action}
        await self.post("/api/job", body)

    async def wait_state(self, wanted: str | tuple[str, ...], timeout_s: float) -> str:
        """Poll the connection state until it starts with (one of) ``wanted``; returns it."""
        wanted = (wanted,) if isinstance(wanted, str) else wanted
        deadline = time.monotonic() + timeout_s
        state = await self.state()
        while not state.startswith(wanted):
            if time.monotonic() > deadline:
                raise AssertionError(f"OctoPrint stayed {state!r}, not {wanted}:\n"
                                     + self.server.serial_log()[-3000:])
            await asyncio.sleep(0.02)
            state = await self.state()
        return state
