"""A web page the operator opens attacks the raw TCP port across protocols, in real headless
Chromium: the page is served from another loopback address (127.0.0.2) and ``fetch()``es
``http://127.0.0.1:<tcp port>/`` with G-code as its body, as any site could. The TCP port
closes the connection at the HTTP request line, so nothing moves and the laser stays off."""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from aiohttp import web
from playwright.async_api import Browser, async_playwright

from tests.e2e.test_mqtt import mpos, tcp_report
from tests.e2e.test_web_e2e import CHROMIUM, CHROMIUM_ARGS
from tests.support.processes import free_port, latency_probe, motiond
from tests.support.undisturbed import assert_prompt

LASER = "[laser]\n"
ATTACK_BODY = "G0 X123 Y77\\nM3 S1000\\nG1 X140 F3000\\n"


def attack_page(tcp_port: int) -> str:
    """Three no-cors POSTs to the TCP port, as the review's page sent them."""
    return f"""<!doctype html><title>cat pictures</title><script>
    (async () => {{
      for (let run = 0; run < 3; run++) {{
        try {{
          await fetch('http://127.0.0.1:{tcp_port}/', {{method: 'POST', mode: 'no-cors',
                      body: '{ATTACK_BODY}'}});
        }} catch (error) {{ console.log('refused: ' + error); }}
      }}
      document.title = 'sent';
    }})();
    </script>"""


@contextlib.asynccontextmanager
async def page_server(html: str) -> AsyncIterator[str]:
    """An HTTP server on 127.0.0.2 serving ``html`` at ``/``; yields its origin."""
    async def index(request: web.Request) -> web.Response:
        return web.Response(text=html, content_type="text/html")

    app = web.Application()
    app.router.add_get("/", index)
    runner = web.AppRunner(app)
    await runner.setup()
    port = free_port()
    await web.TCPSite(runner, "127.0.0.2", port).start()
    try:
        yield f"http://127.0.0.2:{port}"
    finally:
        await runner.cleanup()


async def test_a_page_from_another_address_posting_gcode_to_the_tcp_port_moves_nothing(
    tmp_path: Path,
) -> None:
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install chromium (see .ci/run)")
    async with (
        motiond(tmp_path, LASER) as served,
        latency_probe(served.tcp_port) as probe,
        page_server(attack_page(served.tcp_port)) as origin,
        async_playwright() as playwright,
    ):
        browser: Browser = await playwright.chromium.launch(
            executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = await browser.new_page()
            await page.goto(f"{origin}/")
            await page.wait_for_function("document.title === 'sent'", timeout=20_000)
        finally:
            await browser.close()
        await asyncio.sleep(0.5)  # time for any move the body could have started
        report = await tcp_report(served.tcp_port)
        assert report.startswith("<Idle|"), report
        assert mpos(report)[:2] == [0.0, 0.0], report
        assert not re.search(r"\|FS:\d+,[1-9]", report), report  # no spindle/laser power
        log = (tmp_path / "machine.log").read_text()
        assert log.count("an HTTP request on the line protocol port") >= 1, log
    assert_prompt(probe, least_count=50)  # the operator's ? stayed prompt meanwhile
