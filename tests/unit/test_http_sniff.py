"""The start of a byte stream: an HTTP request line is told from the line protocol."""

from __future__ import annotations

import pytest

from server.protocol.http_sniff import HEAD_LIMIT, HttpSniffer, request_verdict


@pytest.mark.parametrize("head", [
    b"POST / HTTP/1.1\r\nHost: 127.0.0.1:2323\r\n\r\nG0 X123 Y77\nM3 S1000\n",
    b"GET /~ HTTP/1.1\r\n",
    b"OPTIONS * HTTP/1.1\n",
    b"PRI * HTTP/2.0\r\n",
])
def test_a_request_line_is_http(head: bytes) -> None:
    assert request_verdict(head) is True


@pytest.mark.parametrize("head", [b"G0 X1\n", b"?", b"\x18", b"$H\n", b"GET foo\n", b"PLAY x\n",
                                  b"M3 S1000\n", b"!~", b"get / HTTP/1.1\n", b"POST  HTTP/1.1\n"])
def test_anything_else_is_the_line_protocol(head: bytes) -> None:
    assert request_verdict(head) is False


@pytest.mark.parametrize("head", [b"", b"P", b"POS", b"POST ", b"POST /x?a=!~ HTTP/1.1"])
def test_a_possible_request_line_is_undecided_until_its_end(head: bytes) -> None:
    assert request_verdict(head) is None


def test_a_request_split_over_reads_passes_nothing_on_ever() -> None:
    sniffer = HttpSniffer()
    request = b"POST /?!~ HTTP/1.1\r\nHost: x\r\n\r\nG0 X123 Y77\nM3 S1000\n"
    passed = b"".join(sniffer.feed(request[i:i + 3]) for i in range(0, len(request), 3))
    assert passed == b""
    assert sniffer.decided and sniffer.http
    assert sniffer.feed(b"G1 X140 F3000\n") == b""


def test_line_protocol_bytes_pass_on_whole_and_in_order() -> None:
    sniffer = HttpSniffer()
    assert sniffer.feed(b"P") == b""  # could be POST
    assert sniffer.feed(b"LAY job.nc\n?") == b"PLAY job.nc\n?"
    assert sniffer.decided and not sniffer.http
    assert sniffer.feed(b"G0 X1\n") == b"G0 X1\n"


def test_a_first_byte_that_is_realtime_is_never_held() -> None:
    sniffer = HttpSniffer()
    assert sniffer.feed(b"\x18") == b"\x18"
    assert not sniffer.http


def test_an_endless_request_target_is_taken_as_http() -> None:
    sniffer = HttpSniffer()
    assert sniffer.feed(b"GET /" + b"~" * HEAD_LIMIT) == b""
    assert sniffer.decided and sniffer.http
