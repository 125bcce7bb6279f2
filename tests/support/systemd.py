"""Reading a unit file as systemd does, for tests that run its start line the way it would."""

from __future__ import annotations

import pwd
import shlex


def unit_directives(text: str) -> dict[str, list[str]]:
    """``Key=value`` lines by key (a key may repeat, as DeviceAllow= does)."""
    directives: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.startswith(("#", ";", "[")):
            key, value = line.split("=", 1)
            directives.setdefault(key.strip(), []).append(value.strip())
    return directives


def exec_argv(value: str) -> list[str]:
    """An ``ExecStart=`` value as the argv systemd runs: words unquoted, then ``%%`` (the only
    specifier the unit may hold) and ``$$`` each made one character."""
    argv = []
    for word in shlex.split(value):
        for doubled in ("%", "$"):
            parts = word.split(doubled * 2)
            assert all(doubled not in part for part in parts), f"{word!r}: a lone {doubled}"
            word = doubled.join(parts)
        argv.append(word)
    return argv


def service_environment(user: str, notify_socket: str) -> dict[str, str]:
    """The environment systemd gives a system service with ``User=`` (systemd.exec(5))."""
    account = pwd.getpwnam(user)
    return {
        "PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
        "LANG": "C.UTF-8",
        "HOME": account.pw_dir,
        "USER": user,
        "LOGNAME": user,
        "SHELL": account.pw_shell,
        "INVOCATION_ID": "0" * 32,
        "NOTIFY_SOCKET": notify_socket,
    }
