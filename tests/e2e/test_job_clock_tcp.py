"""A job over the raw TCP port of a real ``motiond`` process: ``play`` refuses a job that does
not fit, and ``progress`` shows an honest clock (still in a hold, faster at 150 % feed)."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

from tests.support.processes import motiond

LONG = "G21 G90\nG1 X290 F600\n"  # 29 s at 10 mm/s
EST = re.compile(r"est time: (\d\d):(\d\d):(\d\d)")


class Line:
    """One TCP connection to the server's Grbl port, a line at a time."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    async def send(self, text: str) -> list[str]:
        """Send a line; the lines up to its ``ok`` or ``error:N`` (included)."""
        self.writer.write(text.encode() + b"\n")
        await self.writer.drain()
        lines = []
        while True:
            line = (await asyncio.wait_for(self.reader.readline(), 10)).decode().strip()
            lines.append(line)
            if line == "ok" or line.startswith("error:"):
                return lines

    async def realtime(self, byte: bytes) -> None:
        self.writer.write(byte)
        await self.writer.drain()

    async def remaining_s(self) -> int:
        reply = " ".join(await self.send("progress"))
        match = EST.search(reply)
        assert match, reply
        hours, minutes, seconds = (int(part) for part in match.groups())
        return hours * 3600 + minutes * 60 + seconds


async def test_play_checks_the_fit_and_progress_keeps_an_honest_clock(tmp_path: Path) -> None:
    async with motiond(tmp_path) as served:
        (served.jobs_dir / "neg.nc").write_text("G21 G90\nG1 X10 Y-5 F3000\n")
        (served.jobs_dir / "long.nc").write_text(LONG)
        reader, writer = await asyncio.open_connection("127.0.0.1", served.tcp_port)
        try:
            await asyncio.wait_for(reader.readuntil(b"for help]\r\n"), 5)
            tcp = Line(reader, writer)
            refused = await tcp.send("play neg.nc")
            assert refused[-1] == "error:47", refused
            assert any("Y: 5.000 mm below" in line for line in refused), refused
            assert (await tcp.send("play long.nc"))[-1] == "ok"
            await asyncio.sleep(2.0)
            await tcp.realtime(b"!")
            await asyncio.sleep(0.5)
            held = await tcp.remaining_s()
            await asyncio.sleep(3.0)
            assert await tcp.remaining_s() == held, "a held job's clock stands still"
            await tcp.realtime(b"~")
            await asyncio.sleep(1.0)
            before = await tcp.remaining_s()
            await tcp.realtime(b"\x91" * 5)  # feed override +50 %: 150 %
            await asyncio.sleep(2.0)
            after = await tcp.remaining_s()
            assert before - after >= 5, (before, after)  # 2 s at 1.5x, then / 1.5: about 8 s
            await tcp.send("abort")
        finally:
            writer.close()
