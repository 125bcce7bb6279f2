"""``motiond serve`` runs on asyncio's own loop when its thread may have real-time priority,
else on uvloop when it is installed (``pip install 'motiond[fast]'``), else on asyncio's;
``--loop`` chooses.

uvloop is an optional extra, so these tests put a stand-in ``uvloop`` package (a subclass of
asyncio's loop, defined in a module named ``uvloop``) or a broken one on the path of a real
``motiond`` process, and check which loop it serves on.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.config import StepgenConfig
from server.runtime import realtime
from tests.conftest import REPO

STAND_IN = """\
import asyncio


class Loop(asyncio.SelectorEventLoop):
    pass


def new_event_loop():
    return Loop()
"""
MISSING = "raise ImportError('uvloop is not installed here')\n"


def fake_uvloop(tmp_path: Path, source: str) -> dict[str, str]:
    """The environment of a process whose ``import uvloop`` finds ``source``."""
    package = tmp_path / "site" / "uvloop"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(source)
    path = os.pathsep.join([str(tmp_path / "site"), str(REPO)])
    return {**os.environ, "PYTHONPATH": path, "PYTHONUNBUFFERED": "1"}


def serve(env: dict[str, str], *options: str) -> tuple[str, bytes]:
    """Start motiond, ask ``?`` over TCP, stop it; its log and the report."""
    process = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "--tcp-port", "0", "--http-port", "0", *options],
        cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    assert process.stderr is not None
    log, port = "", None
    deadline = time.monotonic() + 20
    while port is None and time.monotonic() < deadline:
        line = process.stderr.readline()
        log += line
        if "TCP listening on" in line:
            port = int(line.rsplit(":", 1)[1])
    assert port is not None, log
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
            received = b""
            while b"Grbl" not in received:
                received += client.recv(4096)
            client.sendall(b"?")
            report = b""
            while b">" not in report:
                report += client.recv(4096)
    finally:
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
    return log + process.stderr.read(), report


def test_serve_picks_uvloop_when_it_is_installed_and_no_real_time_priority_is_asked(
    tmp_path: Path
) -> None:
    config = tmp_path / "ordinary.toml"
    default = (REPO / "server" / "default.toml").read_text()
    config.write_text(default.replace("[stepgen]\n", "[stepgen]\nrealtime_priority = 0\n"))
    log, report = serve(fake_uvloop(tmp_path, STAND_IN), "--config", str(config))
    assert "(event loop: uvloop)" in log
    assert report.startswith(b"<Idle|")


def test_serve_prefers_asyncio_at_real_time_priority_over_uvloop_when_it_may_have_it(
    tmp_path: Path
) -> None:
    """asyncio's loop with microsecond timers at real-time priority keeps the stall goal under
    load, which uvloop at ordinary priority does not (the streaming benchmark)."""
    log, report = serve(fake_uvloop(tmp_path, STAND_IN))
    if realtime.allowed(StepgenConfig().realtime_priority):  # root, as in CI
        assert "(event loop: asyncio)" in log and "real-time priority 10" in log, log
    else:
        assert "(event loop: uvloop)" in log, log
    assert report.startswith(b"<Idle|")


@pytest.mark.parametrize("options", [(), ("--loop", "asyncio")])
def test_serve_runs_on_asyncio_without_uvloop_or_when_asked(
    tmp_path: Path, options: tuple[str, ...]
) -> None:
    source = MISSING if not options else STAND_IN  # --loop asyncio even with uvloop there
    log, report = serve(fake_uvloop(tmp_path, source), *options)
    assert "(event loop: asyncio)" in log
    assert report.startswith(b"<Idle|")


def test_asking_for_uvloop_without_it_is_refused_with_how_to_install_it(tmp_path: Path) -> None:
    refused = subprocess.run(
        [sys.executable, "-m", "server.cli", "--loop", "uvloop", "--tcp-port", "0",
         "--http-port", "0"],
        cwd=REPO, env=fake_uvloop(tmp_path, MISSING), capture_output=True, text=True,
        timeout=30, check=False)
    assert refused.returncode == 2
    assert "pip install 'motiond[fast]'" in refused.stderr
