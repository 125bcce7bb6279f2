"""``motiond install-service``: a systemd unit that runs motiond at boot, as Klipper's and
Moonraker's installers do, but confined.

The unit runs ``motiond`` from the environment it was installed in with the config, data and
log paths spelled out, ``Type=notify`` (motiond says ``READY=1`` once every listener is open,
:mod:`server.runtime.sdnotify`), ``Restart=on-failure``, and ``LimitRTPRIO`` so the event loop's
thread may take its real-time priority without root (:mod:`server.runtime.realtime`). A system
unit (the default, for a Raspberry Pi: ``sudo``) starts at boot under ``multi-user.target`` as
the given account, never root, hardened as ``systemd-analyze security`` measures it
(:mod:`server.unit`); ``--user`` writes a user unit (no real-time limit: a user manager cannot
raise it; ``loginctl enable-linger`` makes it start at boot).
"""

from __future__ import annotations

import argparse
import grp
import os
import pwd
import shutil
import sys
import tempfile
from pathlib import Path

import platformdirs

from server import paths
from server.errors import ConfigError
from server.unit import Service, UnitError, unit_text

SYSTEM_UNIT_DIR = Path("/etc/systemd/system")
UNIT_NAME = "motiond.service"
UNIT_MODE = 0o644


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sub = commands.add_parser(
        "install-service", help="write a systemd unit that starts motiond at boot",
        description="Write a systemd unit running this motiond with its config, data and log "
        "paths. Then: systemctl daemon-reload && systemctl enable --now motiond")
    sub.add_argument("--config", type=Path, help="machine config (default: the search path's)")
    sub.add_argument("--user", action="store_true",
                     help="a user unit in ~/.config/systemd/user (default: a system unit)")
    sub.add_argument("--run-as",
                     help="the account a system unit runs as, never root (default: the one "
                     "that ran sudo, else the current one)")
    sub.add_argument("--data-dir", type=Path,
                     help="data folder (default: that account's, ~/.local/share/motiond)")
    sub.add_argument("--log-file", type=Path, dest="unit_log_file",  # not this command's log
                     help="the service's log file (default: the data folder's)")
    sub.add_argument("-o", "--output", type=Path,
                     help="where to write the unit; '-' prints it (default: systemd's folder)")


def install_service(args: argparse.Namespace) -> int:
    try:
        service = _service(args)
        text = unit_text(service)
    except (UnitError, ConfigError) as exc:
        problems = exc.problems if isinstance(exc, ConfigError) else [str(exc)]
        for problem in problems:
            print(f"motiond install-service: {problem}", file=sys.stderr)
        return 2
    blocked = None if service.user is None else unreachable(service.executable, service.user)
    if blocked is not None:
        print(f"motiond install-service: warning: {service.user} cannot run "
              f"{service.executable}: {blocked}; the service would fail at every start "
              "(install motiond where that account can read it)", file=sys.stderr)
    if args.output == Path("-"):
        sys.stdout.write(text)
        return 0
    target = args.output or (
        platformdirs.user_config_path("systemd") / "user" / UNIT_NAME if args.user
        else SYSTEM_UNIT_DIR / UNIT_NAME)
    try:
        if service.user is not None:
            _make_folders(service)
        write_unit(target, text)
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


def _service(args: argparse.Namespace) -> Service:
    """What the unit runs, from the options: absolute paths, the account checked."""
    account = None if args.user else _account(args.run_as)
    user_data, user_config = _folders_of(account)
    data_dir = (args.data_dir or user_data).expanduser().resolve()
    config = args.config or next((path for path in (
        Path.cwd() / paths.CONFIG_NAME, user_config / paths.CONFIG_NAME,
        paths.SYSTEM_CONFIG_DIR / paths.CONFIG_NAME) if path.is_file()), None)
    if config is not None:
        config = config.expanduser().resolve()
        paths.check_config_file(config, account.pw_uid if account else os.geteuid())
    return Service(
        executable=_executable(),
        config=config,
        data_dir=data_dir,
        log_file=(args.unit_log_file or data_dir / "motiond.log").expanduser().resolve(),
        user=account.pw_name if account else None,
    )


def _account(name: str | None) -> pwd.struct_passwd:
    """The account a system unit runs as: ``--run-as``, else sudo's caller, else this one;
    root is refused (a motion controller on the network needs none of root's powers)."""
    name = name or os.environ.get("SUDO_USER")
    try:
        account = pwd.getpwnam(name) if name else pwd.getpwuid(os.getuid())
    except KeyError:
        raise UnitError(f"no such user {name or os.getuid()!r}: name an account with "
                        "--run-as USER") from None
    if account.pw_uid == 0:
        raise UnitError(
            "refusing to run motiond as root: name the account it runs as with --run-as USER "
            "(e.g. sudo motiond install-service --run-as pi), or make one for it with "
            "sudo useradd --system --create-home --groups dialout motiond")
    return account


def _folders_of(account: pwd.struct_passwd | None) -> tuple[Path, Path]:
    """The data and config folders of ``account`` (None or the current user: platformdirs',
    ``$XDG_*`` respected; another account, as after sudo: the defaults in its home)."""
    if account is None or account.pw_uid == os.getuid():
        return platformdirs.user_data_path(paths.APP), platformdirs.user_config_path(paths.APP)
    home = Path(account.pw_dir)
    return home / ".local" / "share" / paths.APP, home / ".config" / paths.APP


def _make_folders(service: Service) -> None:
    """The data and log folders, made now and given to the account: the unit's file system
    is read-only but for them, so the service could not make them itself."""
    account = pwd.getpwnam(service.user or "")
    for folder in (service.data_dir, service.log_file.parent):
        missing = [folder, *folder.parents]
        missing = [path for path in missing if not path.exists()]
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        for path in missing:
            if os.geteuid() == 0:
                os.chown(path, account.pw_uid, account.pw_gid)


def unreachable(executable: Path, user: str) -> str | None:
    """Why ``user`` cannot run ``executable`` (a script, then its ``#!`` interpreter), or
    None: a folder it cannot enter (a venv made with a Python in /root) or a file it cannot
    read and execute."""
    account = pwd.getpwnam(user)
    groups = {account.pw_gid, *(g.gr_gid for g in grp.getgrall() if user in g.gr_mem)}
    files = [executable]
    try:
        with executable.open("rb") as script:
            first = script.readline(256)
        if first.startswith(b"#!") and first[2:].split():
            files.append(Path(first[2:].split()[0].decode()))
    except OSError as exc:
        return f"{exc.strerror}: {executable}"
    for file in files:
        real = file.resolve()
        for folder in reversed(real.parents):
            if not _may(folder.stat(), account.pw_uid, groups, 0o1):
                return f"{folder} is closed to it (it holds {real})"
        if not _may(real.stat(), account.pw_uid, groups, 0o5):
            return f"{real} is not readable and executable by it"
    return None


def _may(info: os.stat_result, uid: int, groups: set[int], bits: int) -> bool:
    """Whether the owner, group or other permission ``bits`` of a file grant ``uid``."""
    if uid == 0:
        return True
    shift = 6 if info.st_uid == uid else 3 if info.st_gid in groups else 0
    return (info.st_mode >> shift) & bits == bits


def write_unit(target: Path, text: str) -> None:
    """Write the unit atomically, mode 0644 whatever the umask (systemd warns of, and other
    tools skip, a unit file others may write or cannot read)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
    try:
        with os.fdopen(handle, "w") as file:
            file.write(text)
            os.fchmod(file.fileno(), UNIT_MODE)
        os.replace(temporary, target)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _executable() -> Path:
    """The ``motiond`` script of this environment (a venv's ``bin/motiond``)."""
    beside = Path(sys.executable).with_name("motiond")
    if beside.exists():
        return beside.absolute()
    found = shutil.which("motiond")
    return Path(found).absolute() if found else beside.absolute()
