"""The streaming client of :mod:`benchmarks.bench_streaming`, run in its own process.

Streams a G-code file to a Grbl server over TCP with character counting (a 128-byte window),
on a blocking socket with TCP_NODELAY, and prints one JSON line: lines sent, seconds from the
first line to the last answer, lines refused. Standard library only, so it starts fast and
runs as a script: ``python benchmarks/stream_client.py PORT FILE [--banner] [--check]``.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from collections import deque
from pathlib import Path

WINDOW = 128
HOST = "127.0.0.1"


def client_main(port: int, path: Path, banner: bool, check: bool) -> None:
    """Stream ``path`` with character counting; print a JSON line with the figures."""
    lines = [line.encode() + b"\n" for line in path.read_text().splitlines()]
    sock = socket.create_connection((HOST, port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    pending = b""

    def read_lines() -> list[bytes]:
        nonlocal pending
        data = sock.recv(65536)
        if not data:
            raise ConnectionError("server closed the connection")
        pending += data
        *complete, pending = pending.split(b"\n")
        return [line.strip() for line in complete]

    def command(text: bytes) -> None:
        sock.sendall(text + b"\n")
        while not any(line == b"ok" or line.startswith(b"error") for line in read_lines()):
            pass

    if banner:
        while not any(line.startswith(b"Grbl ") for line in read_lines()):
            pass
    if check:
        command(b"$C")
    unacked: deque[int] = deque()
    used = errors = answered = 0
    started = time.perf_counter()
    index = 0
    while answered < len(lines):
        batch = []
        while index < len(lines) and used + len(lines[index]) <= WINDOW:
            batch.append(lines[index])
            unacked.append(len(lines[index]))
            used += len(lines[index])
            index += 1
        if batch:
            sock.sendall(b"".join(batch))
        for line in read_lines():
            if line == b"ok" or line.startswith(b"error"):
                errors += line.startswith(b"error")
                answered += 1
                used -= unacked.popleft()
    elapsed_s = time.perf_counter() - started
    if check:
        command(b"$C")
    sock.close()
    print(json.dumps({"lines": len(lines), "elapsed_s": elapsed_s, "errors": errors}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port", type=int)
    parser.add_argument("file", type=Path)
    parser.add_argument("--banner", action="store_true", help="wait for the Grbl banner first")
    parser.add_argument("--check", action="store_true", help="stream in check mode ($C)")
    options = parser.parse_args()
    client_main(options.port, options.file, options.banner, options.check)


if __name__ == "__main__":
    main()
