"""``motiond install-service``: a systemd unit that runs motiond at boot, as Klipper's and
Moonraker's installers do.

The unit runs ``motiond`` from the environment it was installed in with the config, data and
log paths spelled out, ``Type=notify`` (motiond says ``READY=1`` once every listener is open,
:mod:`server.runtime.sdnotify`), ``Restart=on-failure``, and ``LimitRTPRIO`` so the event loop's
thread may take its real-time priority without root (:mod:`server.runtime.realtime`). A system
unit (the default, for a Raspberry Pi: ``sudo``) starts at boot under ``multi-user.target`` as
the given user; ``--user`` writes a user unit (no real-time limit: a user manager cannot raise
it; ``loginctl enable-linger`` makes it start at boot).
"""

from __future__ import annotations

import argparse
import getpass
import os
import pwd
import shlex
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import platformdirs

from server import paths

SYSTEM_UNIT_DIR = Path("/etc/systemd/system")
UNIT_NAME = "motiond.service"


@dataclass(frozen=True, slots=True)
class Service:
    """What the unit runs: absolute paths only (systemd has no working directory or ``~``)."""

    executable: Path
    config: Path | None
    data_dir: Path
    log_file: Path
    user: str | None  # None: a user unit
    realtime_priority: int = 10


def unit_text(service: Service) -> str:
    """The unit file's text."""
    command = [str(service.executable), "serve"]
    if service.config is not None:
        command += ["--config", str(service.config)]
    command += ["--data-dir", str(service.data_dir), "--log-file", str(service.log_file)]
    system = service.user is not None
    lines = [
        "[Unit]",
        "Description=motiond networked motion controller",
        *(["After=network-online.target", "Wants=network-online.target"] if system else []),
        "",
        "[Service]",
        "Type=notify",
        "NotifyAccess=main",
        f"ExecStart={shlex.join(command)}",
        *([f"User={service.user}", "SupplementaryGroups=dialout"] if system else []),
        "Restart=on-failure",
        "RestartSec=2",
        "TimeoutStopSec=10",
        # The event loop's thread asks for SCHED_FIFO itself; this lets it without root.
        *([f"LimitRTPRIO={service.realtime_priority}"] if system else []),
        "",
        "[Install]",
        f"WantedBy={'multi-user.target' if system else 'default.target'}",
        "",
    ]
    return "\n".join(lines)


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sub = commands.add_parser(
        "install-service", help="write a systemd unit that starts motiond at boot",
        description="Write a systemd unit running this motiond with its config, data and log "
        "paths. Then: systemctl daemon-reload && systemctl enable --now motiond")
    sub.add_argument("--config", type=Path, help="machine config (default: the search path's)")
    sub.add_argument("--user", action="store_true",
                     help="a user unit in ~/.config/systemd/user (default: a system unit)")
    sub.add_argument("--run-as", default=os.environ.get("SUDO_USER") or getpass.getuser(),
                     help="the account a system unit runs as (default: the one that ran sudo, "
                     "else the current one)")
    sub.add_argument("--data-dir", type=Path,
                     help="data folder (default: that account's, ~/.local/share/motiond)")
    sub.add_argument("--log-file", type=Path, help="log file (default: the data folder's)")
    sub.add_argument("-o", "--output", type=Path,
                     help="where to write the unit; '-' prints it (default: systemd's folder)")


def install_service(args: argparse.Namespace) -> int:
    user_data, user_config = _folders_of(None if args.user else args.run_as)
    data_dir = (args.data_dir or user_data).expanduser().resolve()
    config = args.config or next((path for path in (
        Path.cwd() / paths.CONFIG_NAME, user_config / paths.CONFIG_NAME,
        paths.SYSTEM_CONFIG_DIR / paths.CONFIG_NAME) if path.is_file()), None)
    service = Service(
        executable=_executable(),
        config=config.expanduser().resolve() if config else None,
        data_dir=data_dir,
        log_file=(args.log_file or data_dir / "motiond.log").expanduser().resolve(),
        user=None if args.user else args.run_as,
    )
    text = unit_text(service)
    if args.output == Path("-"):
        sys.stdout.write(text)
        return 0
    target = args.output or (
        platformdirs.user_config_path("systemd") / "user" / UNIT_NAME if args.user
        else SYSTEM_UNIT_DIR / UNIT_NAME)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
    except OSError as exc:
        print(f"motiond: cannot write {target}: {exc.strerror} (a system unit needs sudo; "
              "--user writes a user unit)", file=sys.stderr)
        return 1
    scope = "systemctl --user" if args.user else "sudo systemctl"
    print(f"wrote {target}\nstart it now and at every boot:\n"
          f"  {scope} daemon-reload && {scope} enable --now motiond\n"
          f"follow its log: journalctl {'--user ' if args.user else ''}-u motiond -f "
          f"(or {service.log_file})")
    return 0


def _folders_of(user: str | None) -> tuple[Path, Path]:
    """The data and config folders of ``user`` (None or the current user: platformdirs',
    ``$XDG_*`` respected; another account, as after sudo: the defaults in its home)."""
    if user is None or user == getpass.getuser():
        return platformdirs.user_data_path(paths.APP), platformdirs.user_config_path(paths.APP)
    try:
        home = Path(pwd.getpwnam(user).pw_dir)
    except KeyError:
        raise SystemExit(f"motiond install-service: no such user {user!r}") from None
    return home / ".local" / "share" / paths.APP, home / ".config" / paths.APP


def _executable() -> Path:
    """The ``motiond`` script of this environment (a venv's ``bin/motiond``)."""
    beside = Path(sys.executable).with_name("motiond")
    if beside.exists():
        return beside.absolute()
    found = shutil.which("motiond")
    return Path(found).absolute() if found else beside.absolute()
