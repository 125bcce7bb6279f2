"""The Klipper backend alone: its host CPU per second of motion on the host benchmark's raster.

:mod:`benchmarks.bench_klipper_host` runs the planner and the step generator too (most of its
CPU at 20,000 segments/s). Here their calls into the backend (every piece given to
:meth:`~server.backends.klipper.backend.KlipperBackend.trajectory`, every ``sample``) are
recorded once, then replayed into a fresh backend several times; the best replay's process CPU
is the backend's own per-piece, per-flush and per-message cost. The bytes sent are counted to
show every replay sends the same.

Run: ``python -m benchmarks.bench_klipper_backend [--quick] [--json]``.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from benchmarks import bench_klipper_host as host
from benchmarks.common import BenchResult, standalone


def record(motion_s: float) -> tuple[list[tuple[Any, ...]], float]:
    """The backend's calls during the host benchmark's raster, and the seconds of motion."""
    calls: list[tuple[Any, ...]] = []
    trajectory, sample = host.OfflineBackend.trajectory, host.OfflineBackend.sample

    def on_piece(self: host.OfflineBackend, piece: Any) -> None:
        calls.append((piece,))
        trajectory(self, piece)

    def on_sample(self: host.OfflineBackend, time_s: float, position: object,
                  speed: float) -> None:
        calls.append((time_s, self.now_s))
        sample(self, time_s, position, speed)

    host.OfflineBackend.trajectory = on_piece  # type: ignore[method-assign]
    host.OfflineBackend.sample = on_sample  # type: ignore[method-assign]
    try:
        _, motion_s, _ = host.execute(motion_s)
    finally:
        host.OfflineBackend.trajectory = trajectory  # type: ignore[method-assign]
        host.OfflineBackend.sample = sample  # type: ignore[method-assign]
    return calls, motion_s


def replay(calls: list[tuple[Any, ...]]) -> tuple[float, int]:
    """CPU seconds of one replay into a fresh backend, and the bytes it sent."""
    backend = host.OfflineBackend(host.machine())
    mcu = host.BenchMcu()
    backend.mcu, backend.ready = mcu, True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.configure(oid, mcu.dictionary, backend.cfg.max_error_s * host.CLOCK_HZ)
    backend.follow_power("PA8", 0.001)
    trajectory, sample = backend.trajectory, backend.sample
    started = time.process_time()
    for call in calls:
        if len(call) == 1:
            trajectory(call[0])
        else:
            backend.now_s = call[1]
            sample(call[0], None, 0.0)
    return time.process_time() - started, mcu.link.bytes


def run(quick: bool) -> BenchResult:
    result = BenchResult("klipper-backend", quick)
    calls, motion_s = record(1.0 if quick else 4.0)
    replays = [replay(calls) for _ in range(3 if quick else 8)]
    cpus = sorted(cpu for cpu, _ in replays)
    assert len({sent for _, sent in replays}) == 1, "every replay sends the same bytes"
    print(f"{len(calls):,} calls over {motion_s:.2f} s of motion, {len(replays)} replays")
    print(f"backend CPU per second of motion  best {cpus[0] / motion_s:.3f}  "
          f"median {cpus[len(cpus) // 2] / motion_s:.3f} s/s")
    result.add("klipper backend", "raster", cpu_per_motion_s=(cpus[0] / motion_s, "s/s"),
               median_cpu_per_motion_s=(cpus[len(cpus) // 2] / motion_s, "s/s"))
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__ or ""))
