"""A sender that only asks ``?``: the latency probe of the hardening suite.

Run in its own process (``python -m tests.support.latency_probe HOST PORT``), so the attacks
and the test harness never share its event loop. It sends ``?`` every ``--period-ms`` and times
each status report's round trip until its standard input closes (it prints ``polling`` after
its first answer), then prints one JSON line,
``{"count": N, "p50_ms": .., "p90_ms": .., "p99_ms": .., "max_ms": .., "missed": M}``
(percentiles and worst in milliseconds) where ``missed``
counts requests with no report within a second.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
import time


async def probe(
    host: str, port: int, period_s: float, stop: asyncio.Event, token: str | None
) -> list[float]:
    reader, writer = await asyncio.open_connection(host, port)
    await reader.readline()  # the banner
    if token is not None:  # an operator who logged in: never closed as idle nor capped
        writer.write(f"$AUTH={token}\n".encode())
        while (await reader.readline()).strip() != b"ok":
            pass
    round_trips_s: list[float] = []
    while not stop.is_set():
        sent_s = time.perf_counter()
        writer.write(b"?")
        await writer.drain()
        try:
            while not (await asyncio.wait_for(reader.readline(), 1.0)).startswith(b"<"):
                pass
        except TimeoutError:
            round_trips_s.append(float("inf"))
            continue
        round_trips_s.append(time.perf_counter() - sent_s)
        if len(round_trips_s) == 1:
            print("polling", flush=True)  # the harness starts the attack now
        await asyncio.sleep(max(0.0, period_s - (time.perf_counter() - sent_s)))
    writer.close()
    return round_trips_s


async def wait_for_eof(stop: asyncio.Event) -> None:
    await asyncio.to_thread(sys.stdin.read)
    stop.set()


def summary(round_trips_s: list[float]) -> dict[str, float]:
    answered = sorted(t for t in round_trips_s if t != float("inf"))
    if not answered:
        return {"count": 0, "p50_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0,
                "missed": len(round_trips_s)}
    def at(q: float) -> float:
        return 1000.0 * answered[min(len(answered) - 1, int(q * len(answered)))]
    return {"count": len(answered), "p50_ms": at(0.5), "p90_ms": at(0.9), "p99_ms": at(0.99),
            "max_ms": 1000.0 * answered[-1], "missed": len(round_trips_s) - len(answered)}


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("host")
    parser.add_argument("port", type=int)
    parser.add_argument("--period-ms", type=float, default=10.0)
    parser.add_argument("--token", help="log in with $AUTH first")
    args = parser.parse_args()
    # the instrument must not be what is slow: it runs ahead of the attacks and other load
    # (real-time priority below motiond's own, when allowed, as in CI)
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))
    stop = asyncio.Event()
    watcher = asyncio.create_task(wait_for_eof(stop))
    round_trips_s = await probe(args.host, args.port, args.period_ms / 1000.0, stop, args.token)
    await watcher
    print(json.dumps(summary(round_trips_s)), flush=True)


if __name__ == "__main__":
    asyncio.run(main())
