"""No open door: ``motiond --host 0.0.0.0`` without a token makes one at its first start,
stores it in the data directory (mode 0600) and prints it; without it nothing moves, with it
(or from an address in ``[protocol] trusted_clients``) the machine obeys. Real processes and
sockets; the untrusted client connects from another loopback address (127.0.0.2)."""

from __future__ import annotations

import asyncio
import re
import stat
from pathlib import Path

from tests.e2e.test_mqtt import mpos, tcp_report
from tests.support.processes import motiond

ANY = ("--host", "0.0.0.0")


async def reply_to(port: int, *lines: str, source: str = "127.0.0.1") -> list[str]:
    """The replies (``ok``/``error:N``) to ``lines`` sent on one connection from ``source``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
    try:
        await asyncio.wait_for(reader.readuntil(b"for help]"), 5)
        replies = []
        for line in lines:
            writer.write(line.encode() + b"\n")
            while not (answer := (await asyncio.wait_for(reader.readline(), 5)).decode().strip())\
                    .startswith(("ok", "error:")):
                pass
            replies.append(answer)
        return replies
    finally:
        writer.close()


async def test_an_open_port_gets_a_stored_printed_token_and_nothing_moves_without_it(
    tmp_path: Path,
) -> None:
    async with motiond(tmp_path, args=ANY) as served:
        token_file = served.data_dir / ".token"
        token = token_file.read_text().strip()
        without = await reply_to(served.tcp_port, "G0 X10")
        await asyncio.sleep(0.3)
        unmoved = await tcp_report(served.tcp_port)
        with_token = await reply_to(served.tcp_port, f"$AUTH={token}", "G0 X10")
    printed = (tmp_path / "machine.log").read_text()
    async with motiond(tmp_path, args=ANY) as again:  # the next start uses the same token
        assert (again.data_dir / ".token").read_text().strip() == token
    assert len(token) >= 24
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    assert re.search(rf"^\s+{re.escape(token)}$", printed, re.M), printed
    assert f"$AUTH={token}" in printed and f"?token={token}" in printed
    assert without == ["error:46"]
    assert mpos(unmoved) == [0.0, 0.0]
    assert with_token == ["ok", "ok"]


async def test_trusted_clients_control_without_the_token_and_others_do_not(
    tmp_path: Path,
) -> None:
    trusted = '[protocol]\ntrusted_clients = ["127.0.0.1/32"]\n'
    async with motiond(tmp_path, trusted, args=ANY) as served:
        stranger = await reply_to(served.tcp_port, "G0 X5", source="127.0.0.2")
        await asyncio.sleep(0.2)
        unmoved = await tcp_report(served.tcp_port)
        friend = await reply_to(served.tcp_port, "G0 X5")
        await asyncio.sleep(0.5)
        moved = await tcp_report(served.tcp_port)
    assert stranger == ["error:46"]
    assert mpos(unmoved) == [0.0, 0.0]
    assert friend == ["ok"]
    assert mpos(moved) == [5.0, 0.0]
