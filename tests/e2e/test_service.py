"""motiond as a service: the systemd unit it writes, sd_notify readiness, a log file."""

from __future__ import annotations

import asyncio
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from server.cli import main
from tests.support.processes import AXES_TOML, REPO, free_port


def test_install_service_writes_a_unit_that_systemd_analyze_verifies(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "laser.toml"
    config.write_text(AXES_TOML)
    unit = tmp_path / "motiond.service"
    assert main(["install-service", "--config", str(config), "--data-dir", str(tmp_path / "d"),
                 "--run-as", "root", "-o", str(unit)]) == 0
    printed = capsys.readouterr().out
    assert "systemctl daemon-reload && sudo systemctl enable --now motiond" in printed
    text = unit.read_text()
    for line in ("Type=notify", "Restart=on-failure", "LimitRTPRIO=10", "User=root",
                 "WantedBy=multi-user.target",
                 f"--config {config} --data-dir {tmp_path / 'd'} --log-file "
                 f"{tmp_path / 'd' / 'motiond.log'}"):
        assert line in text
    start = next(line for line in text.splitlines() if line.startswith("ExecStart="))
    assert Path(start.removeprefix("ExecStart=").split()[0]).is_absolute()
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze comes with Debian's systemd (installed by .ci/run)"
    checked = subprocess.run([analyze, "verify", "--man=no", str(unit)],
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked.stderr
    assert "motiond.service" not in checked.stderr, checked.stderr


def test_a_user_unit_has_no_real_time_limit_and_starts_with_the_users_session(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["install-service", "--user", "-o", "-"]) == 0
    text = capsys.readouterr().out
    assert "WantedBy=default.target" in text and "LimitRTPRIO" not in text
    assert "User=" not in text and "Type=notify" in text


async def test_the_server_tells_systemd_it_is_ready_once_listening_and_logs_to_its_file(
        tmp_path: Path) -> None:
    notify_path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as listener:
        listener.bind(str(notify_path))
        listener.setblocking(False)
        config, log_file = tmp_path / "m.toml", tmp_path / "log" / "motiond.log"
        config.write_text(AXES_TOML + f"[jobs]\ndata_dir = '{tmp_path / 'data'}'\n")
        tcp_port = free_port()
        process = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "server.cli", "--log-file", str(log_file), "--config",
            str(config), "--tcp-port", str(tcp_port), "--http-port", str(free_port()),
            cwd=REPO, env={**os.environ, "NOTIFY_SOCKET": str(notify_path)},
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        try:
            loop = asyncio.get_running_loop()
            ready = await asyncio.wait_for(loop.sock_recv(listener, 4096), 60)
            assert ready.decode().splitlines()[0] == "READY=1"
            reader, writer = await asyncio.open_connection("127.0.0.1", tcp_port)  # listening
            writer.close()
            process.send_signal(signal.SIGTERM)
            stopping = await asyncio.wait_for(loop.sock_recv(listener, 4096), 30)
            assert stopping == b"STOPPING=1"
            assert await asyncio.wait_for(process.wait(), 30) == 0
        finally:
            if process.returncode is None:
                process.kill()
                await process.wait()
    logged = log_file.read_text()
    assert f"TCP listening on 127.0.0.1:{tcp_port}" in logged
    assert "stopped" in logged


def test_a_unit_for_another_account_uses_that_accounts_data_folder(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["install-service", "--run-as", "nobody", "-o", "-"]) == 0
    text = capsys.readouterr().out
    home = Path(pwd.getpwnam("nobody").pw_dir).resolve()
    assert "User=nobody" in text
    assert f"--data-dir {home / '.local' / 'share' / 'motiond'} " in text
