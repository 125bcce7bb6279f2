"""The text of motiond's systemd unit: what it runs, confined as systemd's guidance says.

A system unit runs as a non-root account with nothing it does not need, the way
``systemd-analyze security`` measures a unit (it rates this one "OK"): no new privileges, no
capabilities, a read-only system with only the data and log folders (and the config's, where
``$x=`` settings persist beside the config) writable, home folders read-only, a private
``/tmp``, only the serial and pseudo-terminal devices a motion controller opens (through
``dialout``), the kernel, clock, cgroups and other namespaces out of reach, the system calls of
an ordinary service, and ``UMask=0077``. It keeps what motion needs: ``LimitRTPRIO`` lets the
event loop's thread take SCHED_FIFO without a capability (``RestrictRealtime`` stays off), and
the network families a server and its MQTT client use.

Values are written as systemd reads them: ``%`` (specifiers) and ``$`` (variables) doubled in
``ExecStart``, arguments with spaces or quotes double-quoted with ``\\`` escapes; control
characters (a newline would end the directive and start another) are refused.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

HOME_ROOTS = (Path("/home"), Path("/root"), Path("/run/user"))
SERIAL_DEVICES = ("char-ttyS", "char-ttyUSB", "char-ttyACM", "char-ttyAMA", "char-pts")
# A user name systemd accepts in User= (its valid_user_group_name(), relaxed mode's core)
_USER_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]{0,30}")
_PLAIN = re.compile(r"[A-Za-z0-9_@%+=:,./-]+")


class UnitError(ValueError):
    """A value the unit cannot hold (a control character, a bad user name) or root."""


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
    """The unit file's text; raises :class:`UnitError` for a value systemd cannot hold."""
    system = service.user is not None
    lines = [
        "[Unit]",
        "Description=motiond networked motion controller",
        *(["After=network-online.target", "Wants=network-online.target"] if system else []),
        "",
        "[Service]",
        "Type=notify",
        "NotifyAccess=main",
        f"ExecStart={exec_line(command(service))}",
        "Restart=on-failure",
        "RestartSec=2",
        "TimeoutStopSec=10",
        *(_system_lines(service) if system else []),
        "",
        "[Install]",
        f"WantedBy={'multi-user.target' if system else 'default.target'}",
        "",
    ]
    return "\n".join(lines)


def command(service: Service) -> list[str]:
    """The start line's argv (``--log-file`` is an option of ``serve`` as of the command)."""
    argv = [str(service.executable), "serve"]
    if service.config is not None:
        argv += ["--config", str(service.config)]
    return argv + ["--data-dir", str(service.data_dir), "--log-file", str(service.log_file)]


def _system_lines(service: Service) -> list[str]:
    """The account and the confinement of a system unit."""
    user = service.user or ""
    if not _USER_NAME.fullmatch(user):
        raise UnitError(f"{user!r} is not a user name systemd accepts in User=")
    writable = [service.data_dir, service.log_file.parent]
    if service.config is not None:  # $x= settings persist beside the config
        writable.append(service.config.parent)
    everything = [service.executable, *writable]
    in_home = any(path.is_relative_to(root) for path in everything for root in HOME_ROOTS)
    return [
        f"User={user}",
        "SupplementaryGroups=dialout",
        # The event loop's thread asks for SCHED_FIFO itself; this lets it without root.
        f"LimitRTPRIO={service.realtime_priority}",
        "UMask=0077",
        "NoNewPrivileges=yes",
        "CapabilityBoundingSet=",
        "AmbientCapabilities=",
        "ProtectSystem=strict",
        # '-': a folder motiond makes itself at its first start is not a start failure
        f"ReadWritePaths={' '.join(_path_word(path, '-') for path in _unique(writable))}",
        f"ProtectHome={'read-only' if in_home else 'yes'}",
        "PrivateTmp=yes",
        "DevicePolicy=closed",
        *(f"DeviceAllow={group} rw" for group in SERIAL_DEVICES),
        "DeviceAllow=/dev/ptmx rw",
        "ProtectKernelTunables=yes",
        "ProtectKernelModules=yes",
        "ProtectKernelLogs=yes",
        "ProtectControlGroups=yes",
        "ProtectClock=yes",
        "ProtectHostname=yes",
        "ProtectProc=invisible",
        "ProcSubset=pid",
        "RestrictNamespaces=yes",
        "RestrictSUIDSGID=yes",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK",
        "LockPersonality=yes",
        "RemoveIPC=yes",
        "PrivateMounts=yes",
        "SystemCallArchitectures=native",
        "SystemCallFilter=@system-service",
        "SystemCallFilter=~@privileged @obsolete",
        "SystemCallFilter=@chown",  # the pseudo-terminal's group ([serial] pty_group)
        "SystemCallErrorNumber=EPERM",
    ]


def _unique(items: list[Path]) -> list[Path]:
    return list(dict.fromkeys(items))


def exec_line(argv: list[str]) -> str:
    """``argv`` as an ``ExecStart=`` value: each word quoted as systemd unquotes it, ``%``
    and ``$`` doubled so that neither is expanded."""
    return " ".join(_word(arg).replace("%", "%%").replace("$", "$$") for arg in argv)


def _path_word(path: Path, prefix: str = "") -> str:
    """A path in a space-separated path list (``ReadWritePaths=``): specifiers escaped."""
    return _word(prefix + str(path)).replace("%", "%%")


def _word(text: str) -> str:
    """One word: as it is when plain, else double-quoted with ``\\`` and ``"`` escaped."""
    bad = next((char for char in text if ord(char) < 0x20 or ord(char) == 0x7F), None)
    if bad is not None:
        raise UnitError(f"{text!r} holds a control character ({bad!r}): systemd cannot hold "
                        "it in a unit (a newline would start a directive of its own)")
    if text and _PLAIN.fullmatch(text):
        return text
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
