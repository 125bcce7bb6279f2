"""systemd's readiness protocol (``sd_notify``), without a dependency.

Under a ``Type=notify`` unit systemd sets ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the
abstract namespace) and waits for a datagram saying ``READY=1`` before it calls the service
started. motiond sends it once every listener is open, and ``STOPPING=1`` when it shuts down.
Without the variable (run by hand, in Docker, in tests) every call does nothing.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger("motiond.sdnotify")


class Notifier:
    """Sends state lines to systemd's notify socket; never raises."""

    def __init__(self, address: str | None) -> None:
        if address and address.startswith("@"):
            address = "\0" + address[1:]  # the abstract namespace
        self.address = address or None

    @classmethod
    def from_environment(cls) -> Notifier:
        """The socket named by ``$NOTIFY_SOCKET``; the variable is removed so programs motiond
        starts do not notify systemd in its name."""
        return cls(os.environ.pop("NOTIFY_SOCKET", None))

    def notify(self, *states: str) -> bool:
        """Send ``KEY=value`` lines in one datagram; True when sent."""
        if self.address is None:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.setblocking(False)  # a datagram to a local socket: sent or refused at once
                sock.sendto("\n".join(states).encode(), self.address)
        except OSError as exc:
            log.warning("cannot notify systemd at %s: %s", self.address.lstrip("\0"), exc)
            return False
        return True
