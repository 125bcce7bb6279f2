"""motiond under a uid with no account (``docker run --user 1000``, Kubernetes' runAsUser):
nothing looks a name up unless it needs one, and a folder it cannot place is a clear error."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

from tests.support.processes import AXES_TOML, REPO, free_port

NO_ACCOUNT_UID = 12345
_RUN = ("import runpy, site, sys; site.addsitedir(sys.argv.pop(1)); sys.argv[0] = 'motiond'; "
        "runpy.run_module('server.cli', run_name='__main__')")
# Where no uid without an account can run a Python (the venv's is in /root): getpwuid fails
_SIMULATED = ("import pwd; real = pwd.getpwuid\n"
              "def getpwuid(uid): raise KeyError(f'getpwuid(): uid not found: {uid}')\n"
              "pwd.getpwuid = getpwuid\n" + _RUN)


def _python_for_the_uid() -> list[str]:
    """A command running motiond as uid 12345 (no passwd entry) when this runs as root and a
    Python of this version is open to it, else this Python with getpwuid failing."""
    site = sysconfig.get_paths()["purelib"]
    if os.geteuid() == 0 and shutil.which("setpriv"):
        version = f"python{sys.version_info.major}.{sys.version_info.minor}"
        for python in (sys.executable, f"/usr/bin/{version}"):
            if _open_to_all(Path(python)):
                return ["setpriv", f"--reuid={NO_ACCOUNT_UID}", f"--regid={NO_ACCOUNT_UID}",
                        "--clear-groups", python, "-c", _RUN, site]
    return [sys.executable, "-c", _SIMULATED, site]


def _open_to_all(python: Path) -> bool:
    real = python.resolve()
    return real.is_file() and all(folder.stat().st_mode & 0o001 for folder in real.parents)


def _run(base: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*_python_for_the_uid(), *args], cwd=base, capture_output=True, text=True, timeout=60,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO), **env})  # no HOME, no USER


def test_a_uid_without_an_account_serves_and_checks_without_a_traceback() -> None:
    base = Path(tempfile.mkdtemp(prefix="motiond-uid-"))
    try:
        base.chmod(0o777)
        config = base / "m.toml"
        config.write_text(AXES_TOML)
        checked = _run(base, "check-config", str(config), MOTIOND_DATA_DIR=str(base / "d"))
        assert checked.returncode == 0 and "ok" in checked.stdout, checked.stderr
        homeless = _run(base, "check-config", str(config))
        assert homeless.returncode == 1 and "Traceback" not in homeless.stderr
        assert "give one with --data-dir, $MOTIOND_DATA_DIR" in homeless.stderr
        tcp_port = free_port()
        served = subprocess.Popen(
            [*_python_for_the_uid(), "serve", "--config", str(config), "--tcp-port",
             str(tcp_port), "--http-port", str(free_port()), "--data-dir", str(base / "d")],
            cwd=base, stderr=subprocess.PIPE, text=True,
            env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(REPO)})
        try:
            _wait_listening(tcp_port, served)
        finally:
            served.send_signal(signal.SIGTERM)
            _, stderr = served.communicate(timeout=30)
        assert served.returncode == 0 and "Traceback" not in stderr, stderr
        assert f"TCP listening on 127.0.0.1:{tcp_port}" in stderr
    finally:
        shutil.rmtree(base)


def _wait_listening(port: int, process: subprocess.Popen[str]) -> None:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and process.poll() is None:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
            return
        time.sleep(0.05)
    raise AssertionError(f"motiond did not listen on {port}")
