"""``[protocol] trusted_clients`` is strict: what it trusts is what it says."""

from __future__ import annotations

import pytest

from server.config import trusted_client
from tests.unit.test_config import problems_of

BASE_AXES = {"axes": {"x": {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000,
                            "max_mm": 300}}}


def _problem(entry: str) -> str:
    (problem,) = problems_of({**BASE_AXES, "protocol": {"trusted_clients": [entry]}})
    return problem


@pytest.mark.parametrize("entry", ["192.168.1.77/0", "::/0", "0.0.0.0/0"])
def test_a_slash_zero_is_refused_as_trusting_every_address(entry: str) -> None:
    assert "trusts every address, as if no token were set" in _problem(entry)


@pytest.mark.parametrize(("entry", "subnet", "one"), [
    ("10.0.0.5/2", "0.0.0.0/2", "10.0.0.5"),
    ("192.168.1.77/24", "192.168.1.0/24", "192.168.1.77"),
    ("fe80::1/64", "fe80::/64", "fe80::1"),
])
def test_host_bits_set_are_refused_naming_both_fixes(entry: str, subnet: str, one: str) -> None:
    problem = _problem(entry)
    assert problem.startswith("m.toml: [protocol] trusted_clients:")
    assert f"has host bits set: write {subnet} for the subnet or {one} for the one" in problem


def test_an_ipv4_mapped_entry_matches_its_ipv4_client_and_the_reverse() -> None:
    assert trusted_client("127.0.0.1", ["::ffff:127.0.0.1"])
    assert trusted_client("::ffff:10.1.2.3", ["::ffff:10.0.0.0/104"])
    assert trusted_client("::ffff:192.168.1.7", ["192.168.1.0/24"])
    assert not trusted_client("10.1.2.3", ["::ffff:127.0.0.1"])
    assert not trusted_client("192.168.2.7", ["192.168.1.0/24"])
