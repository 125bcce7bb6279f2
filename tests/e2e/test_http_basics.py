"""What a browser or a health check meets on the HTTP port: a plain 404, a health endpoint."""

from __future__ import annotations

import logging

import aiohttp
import pytest

from server.api.server import http_with_api
from server.runtime.clock import RealClock
from server.transports.websocket import HttpTransport
from tests.conftest import make_config
from tests.support.helpers import running


def http_of(app: object) -> HttpTransport:
    return next(t for t in app.transports if isinstance(t, HttpTransport))  # type: ignore[attr-defined]


async def test_an_unknown_path_is_a_plain_text_404_with_a_body_and_a_log_line(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="motiond.http")
    async with running(make_config(), RealClock(), transports=[http_with_api]) as app:
        base = f"http://127.0.0.1:{http_of(app).port}"
        async with aiohttp.ClientSession() as http:
            for path in ("/no-such-page", "/js/missing.js"):
                async with http.get(base + path) as response:
                    body = await response.text()
                    assert response.status == 404
                    assert response.content_type == "text/plain"
                    assert response.headers["X-Content-Type-Options"] == "nosniff"
                    assert body == "404: not found\n"
            async with http.get(base + "/") as page:
                assert page.status == 200 and page.content_type == "text/html"
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("404 ")]
    assert lines and lines[0].startswith("404 GET '/no-such-page' from 127.0.0.1")


async def test_a_burst_of_404s_is_one_log_line_that_counts_the_rest(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="motiond.http")
    async with running(make_config(), RealClock(), transports=[http_with_api]) as app:
        base = f"http://127.0.0.1:{http_of(app).port}"
        async with aiohttp.ClientSession() as http:
            for index in range(50):
                async with http.get(f"{base}/scan-{index}") as response:
                    assert response.status == 404
    logged = [r for r in caplog.records if r.getMessage().startswith("404 ")]
    assert 1 <= len(logged) <= 5  # one a second at most: the burst takes well under 5 s


async def test_health_answers_ok_to_any_host_and_the_page_still_refuses_foreign_hosts() -> None:
    async with running(make_config(), RealClock(), transports=[http_with_api]) as app:
        base = f"http://127.0.0.1:{http_of(app).port}"
        foreign = {"Host": "evil.example"}
        async with aiohttp.ClientSession() as http:
            async with http.get(base + "/health") as health:
                assert (health.status, await health.text()) == (200, "ok\n")
                assert health.headers["Cache-Control"] == "no-store"
            async with http.get(base + "/health", headers=foreign) as from_docker_network:
                assert from_docker_network.status == 200
            async with http.get(base + "/", headers=foreign) as page:
                assert page.status == 403
