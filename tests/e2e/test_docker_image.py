"""The Dockerfile built and run as docs/docker.md says, with podman on a stand-in base image
(:mod:`tests.support.podman`): the health check, the host names, the token, Grbl over TCP
with and without it, a job, stop and restart; and no installer left in the image."""

from __future__ import annotations

import json
import os
import re
import shlex
import socket
import time
import urllib.error
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.podman import IMAGE, build, ensure_base, podman, settings
from tests.support.processes import REPO, free_port


def docs_run_command(name: str, volume: str, tcp_port: int, http_port: int) -> list[str]:
    """docs/docker.md's ``docker run`` as podman's argv: its own container and volume names,
    and its ports published to 127.0.0.1 only, on free ports (the one change)."""
    page = (REPO / "docs" / "docker.md").read_text()
    text = re.search(r"^docker run .*?(?<!\\)$", page, re.M | re.S)
    assert text, "docs/docker.md gives a docker run command"
    argv = shlex.split(text.group(0).replace("\\\n", " "))
    swaps = {"docker": "podman", "motiond-data:/data": f"{volume}:/data",
             "2323:2323": f"127.0.0.1:{tcp_port}:2323", "8080:8080": f"127.0.0.1:{http_port}:8080"}
    argv = [swaps.get(arg, arg) for arg in argv]
    argv[argv.index("--name") + 1] = name
    assert argv[-1] == "motiond"
    return [*argv[1:-1], IMAGE]


@pytest.fixture(scope="module")
def image(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    assert os.geteuid() == 0, "rootful podman: the e2e suite runs as root in CI"
    ensure_base()  # (first: on a new machine no image has its name, and settings() runs it)
    env = settings(tmp_path_factory.mktemp("podman"))
    built = build(REPO, env)
    assert built.returncode == 0, built.stdout[-2000:] + built.stderr[-2000:]
    yield env


class Grbl:
    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.buffer = b""
        self.read_until(rb"Grbl 1\.1\w* \['\$' for help\]\r\n")

    def read_until(self, pattern: bytes) -> str:
        deadline = time.monotonic() + 10
        while not (match := re.search(pattern, self.buffer)) and time.monotonic() < deadline:
            self.buffer += self.sock.recv(65536)
        assert match, self.buffer
        text, self.buffer = self.buffer[:match.end()], self.buffer[match.end():]
        return text.decode()

    def line(self, text: str) -> str:
        self.sock.sendall(text.encode() + b"\n")
        return self.read_until(rb"(ok|error:\d+)\r\n").strip()

    def status(self) -> str:
        self.sock.sendall(b"?")
        return self.read_until(rb"<[^>]*>\r\n").strip()


def _http(port: int, path: str, host: str, data: bytes | None = None,
          headers: dict[str, str] | None = None) -> tuple[int, str]:
    request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", data=data,
                                     headers={"Host": host, **(headers or {})})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, response.read().decode().strip()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def _ready(port: int, name: str, env: dict[str, str]) -> float:
    started, answer = time.monotonic(), None
    while time.monotonic() - started < 60:
        try:
            answer = _http(port, "/health", "127.0.0.1")
        except OSError as exc:
            answer = exc
        if answer == (200, "ok"):
            return time.monotonic() - started
        time.sleep(0.2)
    logged = podman("logs", name, env=env)
    raise AssertionError(f"no /health: {answer!r}; {logged.stdout[-1500:]}{logged.stderr[-1500:]}")


def _wait_status(grbl: Grbl, pattern: str) -> str:
    deadline, status = time.monotonic() + 10, ""
    while time.monotonic() < deadline:
        status = grbl.status()
        if re.search(pattern, status):
            return status
        time.sleep(0.1)
    raise AssertionError(status)


def test_the_image_has_no_installer_and_keeps_its_health_check(image: dict[str, str]) -> None:
    info = json.loads(podman("image", "inspect", IMAGE, env=image).stdout)[0]
    check = info.get("Healthcheck") or info["Config"].get("Healthcheck")
    assert check["Test"] == ["CMD", "python", "-m", "server.health"], info
    assert check["StartPeriod"] > 0
    # motiond's Python (first on PATH) and the official base's /usr/local; the stand-in's
    # Debian python3-pip in /usr/bin is the stand-in's own (the official image has none there)
    probe = podman("run", "--rm", "--entrypoint", "sh", IMAGE, "-c",
                   "for m in pip setuptools wheel; do python -c \"import $m\" 2>/dev/null "
                   "&& echo has-$m; done; ls /opt/motiond/bin/pip* /usr/local/bin/pip* "
                   "/usr/local/lib/python3*/site-packages/pip 2>/dev/null; true", env=image)
    assert probe.stdout.strip() == "", probe.stdout


def test_the_docs_docker_run_serves_by_name_with_the_token_and_restarts(
        image: dict[str, str]) -> None:
    name, volume = f"motiond-ci-{uuid.uuid4().hex[:8]}", f"motiond-ci-{uuid.uuid4().hex[:8]}"
    tcp_port, http_port = free_port(), free_port()
    started = podman(*docs_run_command(name, volume, tcp_port, http_port), env=image)
    assert started.returncode == 0, started.stderr
    try:
        _ready(http_port, name, image)
        token = podman("exec", name, "cat", "/data/.token", env=image).stdout.strip()
        assert len(token) >= 16 and token in podman("logs", name, env=image).stderr
        assert podman("healthcheck", "run", name, env=image).returncode == 0
        for host, status in (("nas.local:8080", 200), ("nas", 200), ("evil.example", 403)):
            assert _http(http_port, "/", host)[0] == status, host
        grbl = Grbl(tcp_port)
        assert grbl.line("G1 X10 F3000") == "error:46"  # no token: read-only
        assert grbl.line(f"$AUTH={token}") == "ok"
        assert grbl.line("G1 X10 F3000") == "ok"
        _wait_status(grbl, r"<Idle\|MPos:10\.000,0\.000,")
        job = b"G21 G90\nM4 S300\nG1 X30 Y0 F1800\nM5\nG0 X5 Y5\n"
        assert _http(http_port, "/upload?name=ci.nc", "127.0.0.1", job)[0] == 401
        assert _http(http_port, "/upload?name=ci.nc", "127.0.0.1", job,
                     {"X-Motiond-Token": token})[0] == 200
        assert grbl.line("play ci.nc").endswith("ok")
        _wait_status(grbl, r"<Idle\|MPos:5\.000,5\.000,")
        grbl.sock.close()
        stop_started = time.monotonic()
        podman("stop", name, timeout_s=60, env=image)
        assert time.monotonic() - stop_started < 9
        state = json.loads(podman("inspect", name, env=image).stdout)[0]["State"]
        logged = podman("logs", name, env=image).stderr
        assert state["ExitCode"] == 0 and "stopped" in logged and "Traceback" not in logged
        assert podman("start", name, env=image).returncode == 0
        _ready(http_port, name, image)
        assert podman("exec", name, "cat", "/data/.token", env=image).stdout.strip() == token
        again = Grbl(tcp_port)
        assert "ci.nc" in again.line("ls") and again.line(f"$AUTH={token}") == "ok"
        again.sock.close()
    finally:
        podman("rm", "-f", "-t", "0", name, env=image)
        podman("volume", "rm", "-f", volume, env=image)


def test_a_bind_mounted_folder_owned_by_uid_10001_holds_the_data(
        image: dict[str, str], tmp_path: Path) -> None:
    data = tmp_path / "motiond-data"
    data.mkdir()
    os.chown(data, 10001, 10001)  # as docs/docker.md says: sudo chown 10001:10001
    name, http_port = f"motiond-ci-{uuid.uuid4().hex[:8]}", free_port()
    started = podman("run", "-d", "--name", name, "-p", f"127.0.0.1:{http_port}:8080",
                     "-v", f"{data}:/data", IMAGE, env=image)
    assert started.returncode == 0, started.stderr
    try:
        _ready(http_port, name, image)
        assert (data / ".token").stat().st_uid == 10001
    finally:
        podman("rm", "-f", "-t", "0", name, env=image)
