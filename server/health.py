"""``python -m server.health`` (and ``motiond health``): whether the server this machine's
config describes answers ``GET /health``; exit status 0 when it answers ``ok``.

The container's ``HEALTHCHECK`` runs it every few seconds, so it is light: the HTTP port and
address come from ``$MOTIOND_HTTP_PORT``, else the config ``serve`` would read
(``$MOTIOND_CONFIG`` or the search path, which extends the built-in machine), read with
``tomllib`` alone, without building the machine (a tenth of a second of CPU, not half a second).
It follows the port wherever it is moved; a fixed 8080 called a moved server unhealthy.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tomllib
import urllib.error
import urllib.request
from importlib import resources
from pathlib import Path
from typing import Any

from server.paths import find_config

TIMEOUT_S = 2.0
WILDCARDS = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}


def health_url(config: Path | None, port: int | None = None, host: str | None = None) -> str:
    """The URL of ``/health`` on the HTTP listener ``config`` (None: the built-in machine's)
    describes, ``port`` and ``host`` winning over it."""
    http: dict[str, Any] = _table(resources.files("server").joinpath("default.toml").read_text())
    if config is not None:
        # a file serve would refuse: its own port is still the best guess
        with contextlib.suppress(OSError, tomllib.TOMLDecodeError):
            http = {**http, **_table(config.read_text())}
    host = host or str(http.get("host", "127.0.0.1"))
    host = WILDCARDS.get(host, host)
    return f"http://{f'[{host}]' if ':' in host else host}:{port or http.get('port', 8080)}/health"


def _table(text: str) -> dict[str, Any]:
    http = tomllib.loads(text).get("http", {})
    return http if isinstance(http, dict) else {}


def check(url: str) -> int:
    """0 when ``url`` answers ``ok``; else 1, saying why on stderr."""
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response:
            answer = response.read(64).decode(errors="replace").strip()
    except (OSError, urllib.error.URLError) as exc:
        print(f"motiond health: {url}: {exc}", file=sys.stderr)
        return 1
    if answer != "ok":
        print(f"motiond health: {url} answered {answer!r}", file=sys.stderr)
        return 1
    return 0


def main() -> int:
    port = os.environ.get("MOTIOND_HTTP_PORT")
    env_config = os.environ.get("MOTIOND_CONFIG")
    config = Path(env_config) if env_config else find_config()
    return check(health_url(config, int(port) if port and port.isdecimal() else None))


if __name__ == "__main__":
    sys.exit(main())
