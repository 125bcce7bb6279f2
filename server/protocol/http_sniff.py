"""Telling an HTTP request from the line protocol at the start of a byte stream.

Any web page the operator opens may ``fetch()`` the raw TCP port (browsers do not block it):
its request line and headers would be answered as bad G-code lines and its body would run.
No G-code sender starts a connection with an HTTP request line (``POST /x HTTP/1.1``: an
upper-case method, a space, a target, a space, ``HTTP/``), so :class:`HttpSniffer` holds the
first bytes of a connection while they could still be one, and says which it is:

* an HTTP request line: nothing of the stream is ever passed on (the connection is closed);
* anything else: the held bytes and all that follows pass on unchanged.

Only a stream starting with an upper-case method name and a space is held until its first line
ends (at most :data:`HEAD_LIMIT` bytes: longer than that is taken as HTTP). Every other stream
is decided by its first byte or two, so a sender's first ``?`` or Ctrl-X is never delayed.
No sockets, no asyncio, no clock.
"""

from __future__ import annotations

import re

METHODS = (b"GET", b"HEAD", b"POST", b"PUT", b"DELETE", b"CONNECT", b"OPTIONS", b"TRACE",
           b"PATCH", b"PRI")
HEAD_LIMIT = 8192  # bytes held at most before the first line ends
_TOKEN = re.compile(rb"[A-Z]*")
_REQUEST_REST = re.compile(rb"[^\s]+ HTTP/\d(?:\.\d)?")


class HttpSniffer:
    """The start of one connection's byte stream: HTTP request or line protocol."""

    def __init__(self) -> None:
        self._head = bytearray()
        self.decided = False  # once True, ``http`` is final
        self.http = False

    def feed(self, data: bytes) -> bytes:
        """Bytes received; returns the bytes that may go on to the line protocol (none while
        undecided, none ever once the stream is found to be HTTP)."""
        if self.decided:
            return b"" if self.http else data
        self._head += data
        verdict = request_verdict(bytes(self._head))
        if verdict is None and len(self._head) <= HEAD_LIMIT:
            return b""
        self.decided, self.http = True, verdict is not False
        head = bytes(self._head)
        self._head.clear()
        return b"" if self.http else head


def request_verdict(head: bytes) -> bool | None:
    """Whether the first bytes of a stream are an HTTP request line (None: cannot tell yet)."""
    token = _TOKEN.match(head)
    assert token is not None  # [A-Z]* always matches
    method = token.group()
    if token.end() == len(head):
        return None if any(name.startswith(method) for name in METHODS) else False
    if head[token.end()] != 0x20 or method not in METHODS:
        return False
    rest = head[token.end() + 1 :]
    end = re.search(rb"[\r\n]", rest)
    if end is None:
        return None
    return _REQUEST_REST.fullmatch(rest[: end.start()]) is not None
