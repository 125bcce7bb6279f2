"""Shutting down with flooding clients connected is clean: exit 0, no traceback logged
(motiond 0.1.0 logged a CancelledError traceback for every client still being paced)."""

from __future__ import annotations

import asyncio
import signal
import sys
from pathlib import Path

from tests.support.processes import AXES_TOML, REPO, free_port

FLOODERS = 15
FLOOD = (b"?" * 100 + b"G0 X1\nG0 X0\n$$\n") * 50  # realtime bytes beyond their pace, lines


async def test_sigterm_with_15_flooding_clients_stops_without_a_traceback(
        tmp_path: Path) -> None:
    config = tmp_path / "m.toml"
    config.write_text(AXES_TOML + f"[jobs]\ndata_dir = '{tmp_path / 'data'}'\n")
    tcp_port = free_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.cli", "--config", str(config), "--tcp-port",
        str(tcp_port), "--http-port", str(free_port()), cwd=REPO,
        stderr=asyncio.subprocess.PIPE)
    assert process.stderr is not None
    await asyncio.wait_for(process.stderr.readuntil(b"TCP listening"), 60)
    stop = asyncio.Event()

    async def flood() -> None:
        _, writer = await asyncio.open_connection("127.0.0.1", tcp_port)
        try:
            while not stop.is_set():
                writer.write(FLOOD)
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()

    flooders = [asyncio.create_task(flood()) for _ in range(FLOODERS)]
    try:
        await asyncio.sleep(1.5)
        process.send_signal(signal.SIGTERM)
        logged = (await asyncio.wait_for(process.stderr.read(), 30)).decode()
        assert await asyncio.wait_for(process.wait(), 30) == 0
    finally:
        stop.set()
        await asyncio.gather(*flooders, return_exceptions=True)
        if process.returncode is None:
            process.kill()
    assert "stopped" in logged
    assert "Traceback" not in logged and "CancelledError" not in logged, logged[-3000:]
