"""A second client that only asks ``?``: status round trips while another client streams.

Run in its own process by :mod:`benchmarks.bench_streaming` (standard library only, so it
starts fast): ``python benchmarks/status_probe.py PORT [--period-ms 10]``. It connects, waits
for the banner, prints ``ready`` and polls ``?`` every period on a blocking socket with
TCP_NODELAY, timing each request to the start of its report (``<...>``). A ``start`` line on
its standard input forgets the round trips so far (the stream began); the end of its standard
input stops it, and it prints one JSON line: ``count``, ``p50_ms``, ``p99_ms``, ``max_ms`` and
``missed`` (requests with no report within a second).
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time

HOST = "127.0.0.1"
TIMEOUT_S = 1.0


class Probe:
    """Polls ``?`` on one connection and keeps the round trips (seconds)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection((HOST, port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.settimeout(TIMEOUT_S)
        self.pending = b""
        self.round_trips_s: list[float] = []
        self.missed = 0

    def wait_for(self, prefix: bytes) -> bool:
        """Read until a line starting with ``prefix``; False after a silent second."""
        while True:
            while b"\n" in self.pending:
                line, self.pending = self.pending.split(b"\n", 1)
                if line.strip().startswith(prefix):
                    return True
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return False
            if not data:
                raise ConnectionError("server closed the connection")
            self.pending += data

    def poll(self, period_s: float, stop: threading.Event, begin: threading.Event) -> None:
        next_s = time.perf_counter()
        while not stop.is_set():
            if begin.is_set():
                begin.clear()
                self.round_trips_s.clear()
                self.missed = 0
            sent_s = time.perf_counter()
            self.sock.sendall(b"?")
            if self.wait_for(b"<"):
                self.round_trips_s.append(time.perf_counter() - sent_s)
            else:
                self.missed += 1
            next_s = max(next_s + period_s, time.perf_counter())
            time.sleep(max(0.0, next_s - time.perf_counter()))

    def summary(self) -> dict[str, float]:
        answered = sorted(self.round_trips_s)
        if not answered:
            return {"count": 0, "p50_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0,
                    "missed": self.missed}

        def at(quantile: float) -> float:
            return 1000.0 * answered[min(len(answered) - 1, int(quantile * len(answered)))]

        return {"count": len(answered), "p50_ms": at(0.5), "p99_ms": at(0.99),
                "max_ms": 1000.0 * answered[-1], "missed": self.missed}


def watch_stdin(stop: threading.Event, begin: threading.Event) -> None:
    for line in sys.stdin:
        if line.strip() == "start":
            begin.set()
    stop.set()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port", type=int)
    parser.add_argument("--period-ms", type=float, default=10.0)
    options = parser.parse_args()
    probe = Probe(options.port)
    if not probe.wait_for(b"Grbl "):
        raise SystemExit("no banner")
    stop, begin = threading.Event(), threading.Event()
    threading.Thread(target=watch_stdin, args=(stop, begin), daemon=True).start()
    print("ready", flush=True)
    probe.poll(options.period_ms / 1000.0, stop, begin)
    probe.sock.close()
    print(json.dumps(probe.summary()), flush=True)


if __name__ == "__main__":
    main()
