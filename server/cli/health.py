"""``motiond health``: whether the server this config describes answers ``GET /health``.

The container's ``HEALTHCHECK`` runs it, so the check follows the port wherever the config,
``$MOTIOND_HTTP_PORT`` or ``--http-port`` moves it (a fixed 8080 called a moved server
unhealthy). Exit status 0 when it answers ``ok``, 1 otherwise.
"""

from __future__ import annotations

import sys
import urllib.error
import urllib.request

from server.config import Config

TIMEOUT_S = 2.0
WILDCARDS = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}


def health_command(config: Config) -> int:
    http = config.core.http
    host = WILDCARDS.get(http.host, http.host)
    url = f"http://{f'[{host}]' if ':' in host else host}:{http.port}/health"
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response:  # noqa: S310
            answer = response.read(64).decode(errors="replace").strip()
    except (OSError, urllib.error.URLError) as exc:
        print(f"motiond health: {url}: {exc}", file=sys.stderr)
        return 1
    if answer != "ok":
        print(f"motiond health: {url} answered {answer!r}", file=sys.stderr)
        return 1
    return 0
