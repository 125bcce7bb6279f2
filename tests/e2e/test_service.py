"""motiond as a service: the systemd unit it writes, sd_notify readiness, a log file."""

from __future__ import annotations

import asyncio
import os
import pwd
import re
import resource
import shutil
import signal
import socket
import stat
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

import pytest

from server.cli import main
from server.service import unreachable
from server.unit import Service, unit_text
from tests.support.processes import AXES_TOML, REPO, free_port
from tests.support.systemd import exec_argv, service_environment, unit_directives

SERVICE_USER = "daemon"  # a system account every Debian has (systemd-analyze warns of nobody)


def _install(tmp_path: Path, *extra: str) -> tuple[int, str]:
    unit = tmp_path / "motiond.service"
    code = main(["install-service", "--run-as", SERVICE_USER, "-o", str(unit), *extra])
    return code, unit.read_text() if unit.exists() else ""


def test_install_service_writes_a_unit_that_systemd_analyze_verifies(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "laser.toml"
    config.write_text(AXES_TOML)
    code, text = _install(tmp_path, "--config", str(config), "--data-dir", str(tmp_path / "d"))
    assert code == 0
    printed = capsys.readouterr().out
    assert "systemctl daemon-reload && sudo systemctl enable --now motiond" in printed
    for line in ("Type=notify", "Restart=on-failure", "LimitRTPRIO=10", f"User={SERVICE_USER}",
                 "WantedBy=multi-user.target", "SupplementaryGroups=dialout", "UMask=0077",
                 "NoNewPrivileges=yes", "ProtectSystem=strict", "PrivateTmp=yes",
                 "CapabilityBoundingSet=\n",
                 f"serve --config {config} --data-dir {tmp_path / 'd'} --log-file "
                 f"{tmp_path / 'd' / 'motiond.log'}"):
        assert line in text + "\n"
    directives = unit_directives(text)
    assert directives["ReadWritePaths"] == [f"-{tmp_path / 'd'} -{tmp_path}"]
    assert Path(exec_argv(directives["ExecStart"][0])[0]).is_absolute()
    _verify(tmp_path / "motiond.service")


def _verify(unit: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze comes with Debian's systemd (installed by .ci/run)"
    checked = subprocess.run([analyze, "verify", "--man=no", str(unit)],
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked.stderr
    assert unit.name not in checked.stderr, checked.stderr


def test_systemd_analyze_security_rates_the_unit_ok(tmp_path: Path) -> None:
    """systemd's own measure of a unit's exposure: 4.0 or lower is "OK" (the unit of
    motiond 0.1.0, like Klipper's and Moonraker's, scored 9.6 "UNSAFE")."""
    home_data = Path("/home/pi/.local/share/motiond")  # ProtectHome=read-only then
    for data_dir in (tmp_path / "d", home_data):
        unit = tmp_path / "motiond.service"
        unit.write_text(unit_text(Service(Path("/opt/motiond/bin/motiond"), None, data_dir,
                                          data_dir / "motiond.log", SERVICE_USER)))
        result = subprocess.run(
            ["systemd-analyze", "security", "--offline=true", "--no-pager", str(unit)],
            capture_output=True, text=True, timeout=60)
        assert "--offline" not in result.stderr, "systemd 250 or later analyses unit files"
        score = re.search(r"Overall exposure level for \S+: ([\d.]+) (\w+)", result.stdout)
        assert score, result.stdout[-500:] + result.stderr
        assert float(score.group(1)) <= 4.0 and score.group(2) == "OK", score.group(0)


def test_install_service_refuses_root_and_names_the_fix(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["install-service", "--run-as", "root", "-o", str(tmp_path / "u")]) == 2
    said = capsys.readouterr().err
    assert "refusing to run motiond as root" in said and "--run-as USER" in said
    assert not (tmp_path / "u").exists()


def test_unit_values_are_escaped_as_systemd_reads_them_and_a_newline_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    odd = tmp_path / 'data 100% $HOME "q" \\x'
    code, text = _install(tmp_path, "--data-dir", str(odd))
    assert code == 0
    argv = exec_argv(unit_directives(text)["ExecStart"][0])
    assert argv[1:] == ["serve", "--data-dir", str(odd), "--log-file", str(odd / "motiond.log")]
    _verify(tmp_path / "motiond.service")
    for bad in ("--data-dir", "--log-file"):
        code, _ = _install(tmp_path / bad, bad, f"{tmp_path}/x\nExecStartPre=/bin/rm -rf /")
        assert code == 2 and not (tmp_path / bad / "motiond.service").exists()
        assert "control character" in capsys.readouterr().err


def test_the_unit_file_is_0644_whatever_the_umask(tmp_path: Path) -> None:
    old = os.umask(0)
    try:
        code, _ = _install(tmp_path, "--data-dir", str(tmp_path / "d"))
    finally:
        os.umask(old)
    assert code == 0
    assert stat.S_IMODE((tmp_path / "motiond.service").stat().st_mode) == 0o644


def test_a_config_another_account_may_write_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "motiond.toml"
    config.write_text(AXES_TOML)
    config.chmod(0o666)
    assert main(["check-config", str(config)]) == 1
    assert f"chmod o-w {config}" in capsys.readouterr().err
    assert _install(tmp_path, "--config", str(config))[0] == 2
    assert "writable by every account" in capsys.readouterr().err
    if os.geteuid() == 0:  # another owner: only root can make one
        config.chmod(0o644)
        os.chown(config, pwd.getpwnam("nobody").pw_uid, -1)
        assert _install(tmp_path, "--config", str(config))[0] == 2
        assert "sudo chown" in capsys.readouterr().err


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


async def test_the_units_start_line_runs_as_systemd_runs_it_to_ready_and_a_clean_stop(
        tmp_path: Path) -> None:
    """ExecStart's argv, run with the environment, account, groups, umask, working folder and
    real-time limit systemd gives it, says READY=1 once listening and stops clean on SIGTERM
    (motiond 0.1.0's unit put --log-file after serve: refused at every start)."""
    root = os.geteuid() == 0
    account = SERVICE_USER if root else pwd.getpwuid(os.getuid()).pw_name
    base = Path(tempfile.mkdtemp(prefix="motiond-unit-"))  # the account must reach it
    try:
        base.chmod(0o755)
        tcp_port, http_port = free_port(), free_port()
        config = base / "motiond.toml"
        config.write_text(AXES_TOML + f"[tcp]\nport = {tcp_port}\n[http]\nport = {http_port}\n")
        data = base / 'data 100% $HOME "q"'
        unit = base / "motiond.service"
        python = _python_the_account_can_run(account, base)
        _install_service(python, "--run-as", account, "--config", str(config),
                         "--data-dir", str(data), "-o", str(unit))
        directives = unit_directives(unit.read_text())
        argv = exec_argv(directives["ExecStart"][0])
        assert argv[0] == str(python.with_name("motiond"))
        runs_as = account if root and unreachable(Path(argv[0]), account) is None else None
        assert runs_as or not root or python == Path(sys.executable), "as the account if it can"
        await _run_as_systemd(argv, directives, runs_as, base, tcp_port)
        log_file = data / "motiond.log"
        logged = log_file.read_text()
        assert f"TCP listening on 127.0.0.1:{tcp_port}" in logged and "stopped" in logged
        if runs_as:  # written by the account, under UMask=0077
            assert log_file.stat().st_uid == pwd.getpwnam(account).pw_uid
            assert stat.S_IMODE(log_file.stat().st_mode) == 0o600
        assert "Traceback" not in logged
    finally:
        shutil.rmtree(base)


def _install_service(python: Path, *args: str) -> None:
    subprocess.run([str(python), "-m", "server.cli", "install-service", *args], check=True,
                   env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, timeout=60)


def _python_the_account_can_run(account: str, base: Path) -> Path:
    """This environment's Python, or when the account cannot run it (a venv of a Python in
    /root, as here) one it can: a venv of the system's Python of this version in ``base``,
    seeing this environment's packages through a .pth file, with its ``motiond`` script."""
    here = Path(sys.executable)
    system = Path(f"/usr/bin/python{sys.version_info.major}.{sys.version_info.minor}")
    if unreachable(here, account) is None or not system.is_file():
        return here
    venv = base / "venv"
    subprocess.run([str(system), "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=60)
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    (venv / "lib" / version / "site-packages" / "this-environment.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n")
    script = venv / "bin" / "motiond"
    script.write_text(f"#!{venv / 'bin' / 'python'}\nimport sys\nfrom server.cli import main\n"
                      "sys.exit(main())\n")
    script.chmod(0o755)
    return venv / "bin" / "python"


async def _run_as_systemd(argv: list[str], directives: dict[str, list[str]], user: str | None,
                          base: Path, tcp_port: int) -> None:
    notify_path = base / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as listener:
        listener.bind(str(notify_path))
        notify_path.chmod(0o777)
        listener.setblocking(False)
        env = service_environment(user or pwd.getpwuid(os.getuid()).pw_name, str(notify_path))
        env["PYTHONPATH"] = str(REPO)  # the one addition: this checkout, not the venv's
        rtprio = int(directives["LimitRTPRIO"][0]) if user else 0
        hard = resource.getrlimit(resource.RLIMIT_RTPRIO)[1]  # raising it needs CAP_SYS_RESOURCE
        rtprio = rtprio if hard == resource.RLIM_INFINITY else min(rtprio, hard)
        process = await asyncio.create_subprocess_exec(
            *argv, cwd="/", env=env, user=user, group=user,
            extra_groups=directives["SupplementaryGroups"] if user else None,
            umask=int(directives["UMask"][0], 8) if user else -1,
            preexec_fn=(lambda: resource.setrlimit(resource.RLIMIT_RTPRIO, (rtprio, rtprio)))
            if rtprio else None,
            stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT)
        try:
            loop = asyncio.get_running_loop()
            ready = await asyncio.wait_for(loop.sock_recv(listener, 4096), 60)
            assert ready.decode().splitlines()[0] == "READY=1"
            _, writer = await asyncio.open_connection("127.0.0.1", tcp_port)
            writer.close()
            process.send_signal(signal.SIGTERM)
            assert await asyncio.wait_for(loop.sock_recv(listener, 4096), 30) == b"STOPPING=1"
            assert await asyncio.wait_for(process.wait(), 30) == 0
        finally:
            if process.returncode is None:
                process.kill()
            output = (await process.communicate())[0].decode()
        assert "Traceback" not in output, output


def test_install_service_warns_when_the_account_cannot_reach_the_program() -> None:
    closed = Path(tempfile.mkdtemp(prefix="motiond-closed-"))  # 0700, in the open /tmp
    try:
        script = closed / "motiond"
        script.write_text("#!/bin/sh\n")
        script.chmod(0o755)
        assert unreachable(script, SERVICE_USER) == f"{closed} is closed to it (it holds {script})"
        closed.chmod(0o755)
        assert unreachable(script, SERVICE_USER) is None
    finally:
        shutil.rmtree(closed)
