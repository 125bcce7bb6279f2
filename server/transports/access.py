"""Who may reach the HTTP port: allowed host names, page origins, tokens, connection slots.

A DNS-rebinding page (``evil.example`` re-pointed at 127.0.0.1) reaches the server with its own
name in ``Host`` and ``Origin``; only names this server answers to are accepted
(``[http] allowed_hosts``, by default the local ones). An IP address cannot be rebound, so an
entry ``0.0.0.0`` or ``::`` (the default when listening on every interface) allows any IPv4 or
IPv6 address literal. Tokens are compared as UTF-8 bytes in constant time, so no string (non
ASCII, lone surrogates) can make the comparison raise.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import logging
import os
import re
import secrets
import socket
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from server.paths import data_dir

if TYPE_CHECKING:
    from server.config import CoreConfig

log = logging.getLogger("motiond.http")
TOKEN_FILE = ".token"  # in the data folder, beside (never in) its jobs/ folder
IpAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1", "*.localhost")
NAME_LOOKUP_TIMEOUT_S = 2.0
_HOST = re.compile(r"(?:\[(?P<ip6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9._-]+))(?::\d{1,5})?")


def tokens_equal(given: str | None, expected: str) -> bool:
    """Constant-time comparison that never raises, whatever characters ``given`` holds."""
    if given is None:
        return False
    return hmac.compare_digest(_utf8(given), _utf8(expected))


def usable_token(given: str | None) -> str | None:
    """A presented token as text that any comparison can take (None when it is not text:
    a header with raw bytes arrives surrogate-escaped and matches no token anyway)."""
    if given is None:
        return None
    try:
        given.encode("utf-8")
    except UnicodeEncodeError:
        return None
    return given


def _utf8(text: str) -> bytes:
    return text.encode("utf-8", "surrogatepass")


def host_name(host: str) -> str | None:
    """The name in a ``Host`` value (or an origin's netloc): lower case, no port, brackets or
    trailing dot; None when the value is not a plain host name or address."""
    match = _HOST.fullmatch(host.strip())
    if match is None:
        return None
    name = match.group("ip6") or match.group("name")
    return name.lower().rstrip(".")


def _ip(name: str) -> IpAddress | None:
    try:
        return ipaddress.ip_address(name)
    except ValueError:
        return None


class HostPolicy:
    """The host names requests may name: exact names, ``*.suffix`` patterns, addresses."""

    def __init__(self, patterns: list[str]) -> None:
        self.any_host = "*" in patterns
        entries = [pattern.strip().lower().rstrip(".") for pattern in patterns if pattern != "*"]
        self._suffixes = tuple(entry[1:] for entry in entries if entry.startswith("*."))
        addresses = [_ip(entry.strip("[]")) for entry in entries]
        self._addresses = {address for address in addresses if address is not None}
        self._names = {entry for entry in entries if not entry.startswith("*.")}
        self._any_v4 = ipaddress.ip_address("0.0.0.0") in self._addresses
        self._any_v6 = ipaddress.ip_address("::") in self._addresses
        self._refused_logged: set[str] = set()

    def allows(self, host: str | None) -> bool:
        """Whether a ``Host`` header value is one of ours (absent: not a browser, allowed)."""
        if host is None or self.any_host:
            return True
        name = host_name(host)
        return name is not None and self.allows_name(name)

    def allows_name(self, name: str) -> bool:
        if name in self._names or name.endswith(self._suffixes):
            return True
        address = _ip(name)
        if address is None:
            return False
        if address in self._addresses:
            return True
        return self._any_v4 if address.version == 4 else self._any_v6

    def note_refused(self, host: str, path: str) -> None:
        """Log a refused host once (a rebinding page retries; the log must not flood)."""
        if host in self._refused_logged or len(self._refused_logged) >= 64:
            return
        self._refused_logged.add(host)
        log.warning("refused %s for host %r: not in [http] allowed_hosts", path, host)


def origin_allowed(
    origin: str | None, host: str | None, allowed_origins: list[str], hosts: HostPolicy
) -> bool:
    """Whether a request may act on the machine: no ``Origin`` (not a browser), an origin
    listed in ``[http] allowed_origins`` ("*" allows any), or the page's own origin when that
    names an allowed host. A page on another site must not drive the machine."""
    if origin is None or "*" in allowed_origins or origin in allowed_origins:
        return True
    try:
        netloc = urlsplit(origin).netloc
    except ValueError:
        return False
    if host is None or netloc.lower() != host.strip().lower():
        return False
    return hosts.allows(netloc)


def default_hosts(bind_host: str, machine_names: list[str]) -> list[str]:
    """The local names, the bound address (a wildcard: any address) and this machine's."""
    bound = "0.0.0.0" if bind_host in ("", "0.0.0.0") else bind_host
    names = [*LOCAL_NAMES, bound, *machine_names]
    if bind_host == "::":
        names.append("0.0.0.0")  # a dual-stack wildcard also takes IPv4
    return list(dict.fromkeys(name.lower() for name in names if name))


async def machine_names() -> list[str]:
    """This machine's own names (``gethostname``, ``getfqdn``); the DNS lookup runs in a
    thread and is given up after a short while."""
    names = [socket.gethostname()]
    try:
        fqdn = await asyncio.wait_for(asyncio.to_thread(socket.getfqdn), NAME_LOOKUP_TIMEOUT_S)
    except (TimeoutError, OSError) as exc:
        log.warning("could not look up this machine's full name: %r", exc)
    else:
        names.append(fqdn)
    return names


class ConnectionSlots:
    """WebSocket connections counted apart by whether they presented the token, so sockets
    without it can never lock out an operator who has it."""

    def __init__(self, authenticated_max: int, unauthenticated_max: int) -> None:
        self.limits = {True: authenticated_max, False: unauthenticated_max}
        self.open = {True: 0, False: 0}

    def take(self, authenticated: bool) -> bool:
        if self.open[authenticated] >= self.limits[authenticated]:
            return False
        self.open[authenticated] += 1
        return True

    def release(self, authenticated: bool) -> None:
        self.open[authenticated] -= 1

    def promote(self) -> None:
        """A connection presented the token after it was admitted without it."""
        self.open[False] -= 1
        self.open[True] += 1

    @property
    def total(self) -> int:
        return self.open[True] + self.open[False]


def is_loopback(host: str) -> bool:
    """Whether a bind address only reaches this machine."""
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def close_open_door(core: CoreConfig) -> Path | None:
    """No open door: when the TCP or HTTP port listens beyond loopback without a token, use
    the token stored in the data directory (made at the first such start, readable by this
    user only) for every port that has none. Returns the token file when it did so."""
    env = os.environ.get("MOTIOND_TOKEN") or None
    line_token, http_token = core.protocol.token or env, core.http.token or env
    open_tcp = core.tcp.enabled and not is_loopback(core.tcp.host) and line_token is None
    open_http = core.http.enabled and not is_loopback(core.http.host) and http_token is None
    if not (open_tcp or open_http):
        return None
    path = data_dir(core) / TOKEN_FILE
    token = _stored_token(path)
    if line_token is None:
        core.protocol.token = token
    if http_token is None:
        core.http.token = token
    return path


def _stored_token(path: Path) -> str:
    """The token in ``path``, made (random, mode 0600) when the file does not exist yet."""
    try:
        token = path.read_text().strip()
    except FileNotFoundError:
        token = ""
    if len(token) >= 8:
        return token
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(24)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w") as handle:
        handle.write(token + "\n")
    os.chmod(path, 0o600)
    return token
