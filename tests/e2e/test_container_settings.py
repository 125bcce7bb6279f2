"""What a container is configured with: host names from ``$MOTIOND_ALLOWED_HOSTS`` and a
health check (``motiond health``) that follows the HTTP port wherever it is moved."""

from __future__ import annotations

import asyncio
import os
import sys
import urllib.error
import urllib.request
from pathlib import Path

from tests.support.processes import REPO, free_port, motiond


def _status(port: int, host: str) -> int:
    request = urllib.request.Request(f"http://127.0.0.1:{port}/", headers={"Host": host})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return int(response.status)
    except urllib.error.HTTPError as exc:
        return exc.code


async def test_motiond_allowed_hosts_adds_the_hosts_names_to_the_local_ones(
        tmp_path: Path) -> None:
    async with motiond(tmp_path, env={"MOTIOND_ALLOWED_HOSTS": "nas.local, nas"}) as served:
        for host, status in (("nas.local:8080", 200), ("nas", 200), ("localhost", 200),
                             ("evil.example", 403)):
            assert await asyncio.to_thread(_status, served.http_port, host) == status, host


async def test_motiond_health_asks_the_port_the_server_was_given(tmp_path: Path) -> None:
    async with motiond(tmp_path) as served:
        config = tmp_path / "machine.toml"
        for port, code in ((served.http_port, 0), (free_port(), 1)):
            checked = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "server.cli", "health", "--config", str(config), cwd=REPO,
                env={**os.environ, "MOTIOND_HTTP_PORT": str(port)},
                stderr=asyncio.subprocess.PIPE)
            _, said = await checked.communicate()
            assert checked.returncode == code, said


async def test_the_image_health_check_follows_the_port_of_motiond_config(tmp_path: Path) -> None:
    """``python -m server.health`` (the HEALTHCHECK) reads the port from $MOTIOND_CONFIG (a
    file extending the built-in machine) without building the machine."""
    async with motiond(tmp_path) as served:
        for port, code in ((served.http_port, 0), (free_port(), 1)):
            moved = tmp_path / f"moved-{port}.toml"
            moved.write_text(f"http.port = {port}\n")
            checked = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "server.health", cwd=tmp_path,
                env={**os.environ, "PYTHONPATH": str(REPO), "MOTIOND_CONFIG": str(moved)},
                stderr=asyncio.subprocess.PIPE)
            _, said = await checked.communicate()
            assert checked.returncode == code, said
