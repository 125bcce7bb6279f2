"""1,100 half-sent HTTP requests cannot lock the TCP operator out: pending connections are
capped and closed early, so descriptors stay for the operator (motiond 0.1.0 gave the sender
no banner until ``request_timeout_s``)."""

from __future__ import annotations

import asyncio
import resource
import sys
import time
from pathlib import Path

from tests.support.processes import AXES_TOML, REPO, free_port, stop_process

HALF_SENT = 1100
SERVER_DESCRIPTORS = 1024  # the usual soft limit of a service or a container


async def test_a_flood_of_half_sent_requests_leaves_the_tcp_operator_served(
        tmp_path: Path) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, 4096)), hard))
    config = tmp_path / "m.toml"
    config.write_text(AXES_TOML + f"[jobs]\ndata_dir = '{tmp_path / 'data'}'\n")
    tcp_port, http_port = free_port(), free_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.cli", "--config", str(config), "--tcp-port",
        str(tcp_port), "--http-port", str(http_port), "--log-level", "error", cwd=REPO,
        preexec_fn=lambda: resource.setrlimit(
            resource.RLIMIT_NOFILE, (SERVER_DESCRIPTORS, SERVER_DESCRIPTORS)),
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
    writers: list[asyncio.StreamWriter] = []
    try:
        await _listening(http_port)
        for _ in range(HALF_SENT):
            try:
                _, writer = await asyncio.open_connection("127.0.0.1", http_port)
            except OSError:
                continue  # refused at once: that is the point
            writer.write(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # never ends
            writers.append(writer)
        await asyncio.sleep(0.3)
        started = time.monotonic()
        reader, writer = await asyncio.wait_for(asyncio.open_connection("127.0.0.1", tcp_port), 5)
        banner = await asyncio.wait_for(reader.readuntil(b"Grbl 1.1"), 5)
        waited_s = time.monotonic() - started
        writer.close()
        assert b"Grbl 1.1" in banner and waited_s < 2.0, (banner, waited_s)
    finally:
        for writer in writers:
            writer.close()
        await stop_process(process)


async def _listening(port: int) -> None:
    for _ in range(400):
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
        except OSError:
            await asyncio.sleep(0.05)
            continue
        writer.close()
        return
    raise AssertionError(f"motiond did not listen on {port}")
