"""Motion that must go on undisturbed during an attack, and the trace that proves it did.

The hardening tests run a real ``motiond`` with the simulated machine writing every tick's
sample to a CSV file (``[backend] trace_csv``, written when the server stops). While an attack
runs, :func:`keep_moving` streams long moves from a logged-in sender; afterwards
:func:`trace_jumps` reads the trace: the longest time between two ticks and the longest
distance the tool moved from one tick to the next (a stalled loop makes the next tick late
and the tool jump: 5.7-6.6 mm in one tick under the realtime flood of issue 23, nominal
0.05 mm at 50 mm/s and 1 kHz).
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import math
from collections.abc import AsyncIterator
from pathlib import Path

FEED_MM_MIN = 3000.0  # 50 mm/s: one tick at 1 kHz moves 0.05 mm
# The operator's ``?`` during an attack (tests.support.latency_probe, every 10 ms). The goal
# is 10 ms at the 99th percentile, met by nearly every attack when the machine is quiet (p99
# 0.8-7.7 ms, 10.4 ms once beside the /api frames; the two that stream 2 MB ahead 1.1-3.6 ms
# since held-back input is skimmed: before, 22-24 ms at p90, the loop parsing the attacker's
# whole stream line by line as it arrived, ~1 s of loop time in 1.5-4.4 ms turns).
# This 2-core machine, shared by five sessions' tests
# (load 5-9) and running Python about 3x slower than the one that set the goal, gave up to
# 12-14 ms at p90 and 20 ms at p99, and one round trip of 97 ms with two CPU hogs beside the
# suite; the old code: 261 ms to 7 s.
P90_MS = 20.0
P99_MS = 40.0
WORST_MS = 150.0
# The longest time between two ticks while the tool moves (a late tick is a jump: speed x
# gap, 2.5 mm at 50 mm/s for this bound). Measured at load 2-4: 1.4-4.6 ms for most attacks,
# 8-14 ms beside the /api floods and deep JSON; the streams of 2 MB ahead 2-5.1 ms (60-68 ms
# before, a 3 mm jump). The loop runs at real-time priority where allowed (as in CI), so
# other processes hardly make it late.
TICK_GAP_MS = 50.0


def trace_toml(path: Path) -> str:
    """The config section that makes the simulated machine write its trace to ``path``."""
    return f"[backend]\ntrace_csv = '{path}'\n"


@contextlib.asynccontextmanager
async def keep_moving(tcp_port: int, token: str | None = None) -> AsyncIterator[None]:
    """Moves back and forth (X10 <-> X250 at 50 mm/s) from a sender of its own while the
    block runs, one line at a time; replies are not checked (an attack may hold or reset)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", tcp_port)
    if token is not None:
        writer.write(f"$AUTH={token}\n".encode())

    moving = asyncio.Event()

    async def move() -> None:
        for index in range(1_000_000):
            writer.write(b"G1 X%d Y20 F%d\n" % (250 if index % 2 else 10, FEED_MM_MIN))
            await writer.drain()
            if not (await reader.readline()).startswith(b"ok"):  # refused, or a push
                await asyncio.sleep(0.1)  # (a banner, held, reset, owned by another)
            elif index > 0:
                moving.set()  # a move runs and the next is planned

    task = asyncio.create_task(move())
    try:
        await asyncio.wait_for(moving.wait(), 10)
        yield
    finally:
        task.cancel()
        writer.close()
        with contextlib.suppress(asyncio.CancelledError, ConnectionError):
            await task


def assert_prompt(probe: dict[str, float], least_count: int = 80) -> None:
    """The latency probe's summary: no ``?`` missed, 90 % within :data:`P90_MS`, 99 % within
    :data:`P99_MS`, the worst within :data:`WORST_MS` (see there for why not 10 ms)."""
    assert probe["missed"] == 0 and probe["count"] > least_count, probe
    assert probe["p90_ms"] < P90_MS and probe["p99_ms"] < P99_MS, probe
    assert probe["max_ms"] < WORST_MS, probe


def trace_jumps(path: Path) -> dict[str, float]:
    """From a trace file: ``max_gap_ms`` between two ticks while the tool moves (from a
    tick at speed: ticks pause while nothing moves, and a hold or a reset is such a pause),
    ``max_step_mm`` moved in one tick, ``moved_mm`` in all (motion ran at all), ``max_y_mm``
    (the moving sender stays at Y20: anything beyond moved by another's lines)."""
    gap_s = step_mm = moved_mm = max_y_mm = 0.0
    previous: list[float] | None = None
    with path.open(newline="") as handle:
        rows = csv.reader(handle)
        header = next(rows)
        axes = [index for index, name in enumerate(header) if name.endswith("_mm")]
        speed = header.index("speed_mm_s")
        for row in rows:
            values = [float(value) for value in row]
            if previous is not None:
                step = math.dist([values[i] for i in axes], [previous[i] for i in axes])
                if step > 0.0 and previous[speed] > 0.0:
                    gap_s = max(gap_s, values[0] - previous[0])
                step_mm, moved_mm = max(step_mm, step), moved_mm + step
            previous = values
            max_y_mm = max(max_y_mm, values[header.index("y_mm")])
    return {"max_gap_ms": 1000.0 * gap_s, "max_step_mm": step_mm, "moved_mm": moved_mm,
            "max_y_mm": max_y_mm}
