"""Which bind addresses are loopback, which clients are trusted, when a token is made."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from server.config import trusted_client
from server.transports.access import close_open_door, is_loopback
from tests.conftest import make_config


@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.0.0.2", True), ("::1", True), ("localhost", True),
    ("0.0.0.0", False), ("::", False), ("", False), ("192.168.1.5", False), ("cnc.local", False),
])
def test_loopback_bind_addresses(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_trusted_clients_are_addresses_and_subnets_and_empty_trusts_nobody() -> None:
    entries = ["192.168.1.0/24", "10.0.0.5", "fd00::/8"]
    assert trusted_client("192.168.1.77", entries)
    assert trusted_client("::ffff:192.168.1.77", entries)  # IPv4 on a dual-stack socket
    assert trusted_client("10.0.0.5", entries) and not trusted_client("10.0.0.6", entries)
    assert trusted_client("fd00::1", entries)
    assert not trusted_client("127.0.0.1", entries)
    assert not trusted_client("192.168.1.77", [])
    assert not trusted_client("not an address", entries) and not trusted_client(None, entries)


def test_a_bad_trusted_client_entry_is_a_config_error() -> None:
    with pytest.raises(Exception, match="not an address or subnet"):
        make_config(protocol={"trusted_clients": ["192.168.1.0/33"]})


def test_only_a_port_open_beyond_loopback_without_a_token_gets_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("MOTIOND_TOKEN", raising=False)
    local = make_config(jobs={"data_dir": str(tmp_path)}).core
    assert close_open_door(local) is None and local.protocol.token is None
    given = make_config(jobs={"data_dir": str(tmp_path)}, tcp={"host": "0.0.0.0"},
                        http={"host": "0.0.0.0", "token": "http-token"},
                        protocol={"token": "line-token"}).core
    assert close_open_door(given) is None
    exposed = make_config(jobs={"data_dir": str(tmp_path)}, http={"host": "0.0.0.0"}).core
    path = close_open_door(exposed)
    assert path == tmp_path / ".token" and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert exposed.protocol.token == exposed.http.token == path.read_text().strip()
