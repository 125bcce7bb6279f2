"""The Klipper backend's host half: CPU per second of motion, bytes on the wire, step error.

A raster of 0.025 mm segments at up to 500 mm/s (20,000 segments/s at full speed, power
changing every segment and following the speed, M4, the laser's PWM timed from the pieces at
most every millisecond) runs through the real planner, step generator (ticking once a flush, as
it does for this backend) and :class:`~server.backends.klipper.backend.KlipperBackend` on a
virtual clock; the
MCU side is a sink that frames each burst of messages into blocks as the link does and
counts the bytes. Reported:

* host CPU seconds per second of motion (< 1 means the host keeps up in real time);
* bytes per second on the wire against a 250,000-baud link (25,000 bytes/s of 8N1);
* how early the compressed steps land against their exact times (the bound is 25 µs).

First, the rig benchmark's raster and circles (:mod:`.klipper_rig_jobs`, F6000, the laser on at
a constant S) through the same parts without the line path, ticking when the backend asks (as
the server does): the CPU per block of the per-block work (the planner's pops, the step
generator, the pieces, the backend's samples). Then the same jobs (and the long moves) with
the process asleep ``COLD_GAP_S`` before each tick, as the server sleeps between its sparse
ticks: the same work, from cold caches (on the shared 2-core VM it costs several times as
much: why each wake-up of the server is worth removing, more than the Python it runs).

Run: ``python -m benchmarks klipper-host [--quick] [--json]`` (``klipper`` measures the real
firmware against Klipper's own host: :mod:`benchmarks.bench_klipper`).
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from benchmarks.common import BenchResult, standalone
from benchmarks.klipper_rig_hosts import (
    ACCEL_MM_S2,
    JUNCTION_DEVIATION_MM,
    LASER_S_MAX,
    MAX_RATE_MM_S,
    STEPS_PER_MM,
    TRAVEL_MM,
)
from benchmarks.klipper_rig_jobs import LASER, SPEED_MM_S, Job
from benchmarks.klipper_rig_jobs import circles as rig_circles
from benchmarks.klipper_rig_jobs import long_moves as rig_long_moves
from benchmarks.klipper_rig_jobs import raster as rig_raster
from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.dictionary import Dictionary
from server.config_loader import build_config
from server.machine.parts import planner_settings
from server.motion.backend import PowerLaw
from server.motion.moves import Action, Move, MoveKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator

CLOCK_HZ = 72_000_000
BAUD_BYTES_S = 250_000 / 10
SEGMENT_MM, RASTER_MM_S, LINE_MM = 0.025, 500.0, 300.0


def dictionary(clock_hz: float = CLOCK_HZ) -> Dictionary:
    """The data dictionary of an MCU that only steps and drives a PWM output."""
    return Dictionary({"commands": {"queue_step oid=%c interval=%u count=%hu add=%hi": 2,
                                    "set_next_step_dir oid=%c dir=%c": 3,
                                    "reset_step_clock oid=%c clock=%u": 4,
                                    "queue_pwm_out oid=%c clock=%u value=%hu": 5},
                       "config": {"CLOCK_FREQ": clock_hz, "PWM_MAX": 255}})


class WireCount:
    """Frames each burst of messages into blocks of at most 59 payload bytes, as the link
    packs a burst (the window is never full here: the MCU acknowledges at once)."""

    def __init__(self) -> None:
        self.bytes = self.blocks = self.messages = 0

    def send(self, *messages: bytes) -> None:
        block = 0
        for message in messages:
            if block and block + len(message) > PAYLOAD_MAX:
                self.bytes, self.blocks, block = self.bytes + block + 5, self.blocks + 1, 0
            block += len(message)
        if block:
            self.bytes, self.blocks = self.bytes + block + 5, self.blocks + 1
        self.messages += len(messages)

    def sample(self) -> None:
        """The backend's tick reads the device here: there is none."""


class BenchMcu:
    def __init__(self) -> None:
        self.dictionary = dictionary()
        self.clock = ClockSync(CLOCK_HZ)
        self.clock.reset(0.0, 0)
        self.move_count = 1 << 30
        self.link = WireCount()


class OfflineBackend(KlipperBackend):
    """The real backend whose MCU clock runs on the virtual time of the benchmark."""

    now_s = 0.0

    def _now_clock(self) -> float:
        return self._clock_at(self.now_s)


class Listener:
    def on_action(self, action: Action) -> None: ...
    def on_idle(self) -> None: ...
    def on_hold_stopped(self) -> None: ...


def machine() -> Any:
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 10000, "max_mm": 400}
            for a in "xy"}
    pins = {"x": {"step_pin": "PB13", "dir_pin": "PB12"}, "y": {"step_pin": "PB10",
                                                               "dir_pin": "PB2"}}
    return build_config({"axes": axes, "backend": {
        "kind": "klipper", "serial": "/dev/null", "axes": pins, "outputs": {"PA8": {}}}}).core


def raster(motion_s: float) -> list[Move]:
    """Zig-zag lines of short segments, S changing every segment."""
    moves, x, y, direction = [], 0.0, 0.0, 1
    per_line = int(LINE_MM / SEGMENT_MM)
    for _ in range(int(motion_s * RASTER_MM_S / LINE_MM) + 1):
        for k in range(per_line):
            x += direction * SEGMENT_MM
            moves.append(Move((x, y), RASTER_MM_S, MoveKind.FEED, ToolMode.CCW, 200 + k % 800))
        y += 0.1
        moves.append(Move((x, y), RASTER_MM_S, MoveKind.FEED, ToolMode.CCW, 0.0))
        direction = -direction
    return moves


def rig_machine() -> Any:
    """The rig benchmark's machine (``python -m benchmarks klipper``): 80 steps/mm,
    2,000 mm/s², 200 mm/s, junction deviation 0.01 mm."""
    axes = {a: {"steps_per_mm": STEPS_PER_MM, "max_rate_mm_s": MAX_RATE_MM_S,
                "accel_mm_s2": ACCEL_MM_S2, "max_mm": TRAVEL_MM} for a in "xy"}
    pins = {"x": {"step_pin": "PA0", "dir_pin": "PA1"}, "y": {"step_pin": "PA3",
                                                              "dir_pin": "PA4"}}
    return build_config({"axes": axes, "planner": {"junction_deviation_mm":
                                                   JUNCTION_DEVIATION_MM},
                         "backend": {"kind": "klipper", "serial": "/dev/null", "axes": pins,
                                     "outputs": {"PA8": {}}}}).core


def rig_moves(job: Job) -> list[Move]:
    """A rig job's path as moves at F6000, the laser on (M3) along the raster's lines and the
    circles, off on the raster's step-overs."""
    moves, x_line = [], job.start[1]
    on = round(LASER * LASER_S_MAX)
    for x, y in job.path:
        stepover = y != x_line and job.name == "raster"
        x_line = y
        moves.append(Move((x, y), SPEED_MM_S, MoveKind.FEED, ToolMode.CW,
                          0.0 if stepover else on))
    return moves


def execute(motion_s: float, job: Job | None = None,
            pause_s: float = 0.0) -> tuple[float, float, OfflineBackend]:
    """CPU seconds and seconds of motion for a raster of ``motion_s`` seconds (or a rig job,
    ``job``, repeated for about ``motion_s`` seconds); ``pause_s``: asleep before each tick."""
    core = machine() if job is None else rig_machine()
    backend = OfflineBackend(core, record=True)
    backend.mcu, backend.ready = BenchMcu(), True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.configure(oid, backend.mcu.dictionary, backend.cfg.max_error_s * CLOCK_HZ)
    start = (0.0, 0.0) if job is None else job.start
    planner = Planner(planner_settings(core), start)
    for axis, mm in zip(backend.axes, start, strict=True):
        axis.position = round(mm * axis.steps_per_mm)
    stepgen = StepGenerator(planner, backend, backend.steps_per_mm, Listener())
    backend.follow_power("PA8", 0.001)
    if job is None:  # the laser module's law: S/1000 of 80 %, M4
        stepgen.follow_power(lambda move, nominal_mm_s: PowerLaw(
            0.0, move.s_value / 1000 * 0.8 / nominal_mm_s, 0.8))
        all_moves = raster(motion_s)
    else:  # M3: a constant S/1000 while on
        stepgen.follow_power(lambda move, nominal_mm_s: PowerLaw(move.s_value / LASER_S_MAX)
                             if move.s_value > 0.0 else None)
        all_moves = rig_moves(job)
    moves = iter(all_moves)
    pending: Move | None = next(moves)
    now_s, started, ticks = 0.0, time.process_time(), 0
    stepgen.tick(now_s)
    while pending is not None or not stepgen.idle:
        ticks += 1
        while pending is not None and not planner.is_full():
            planner.append(pending)
            pending = next(moves, None)
        stepgen.request_start()
        # the rig's jobs tick as the server's ticks do: when the backend needs a sample
        now_s = now_s + stepgen.tick_s if job is None else stepgen.next_tick_s(now_s, now_s)
        backend.now_s = now_s
        if pause_s:
            time.sleep(pause_s)  # not CPU: process_time counts only the work
        stepgen.tick(now_s)
    backend.segments = len(all_moves)  # type: ignore[attr-defined]
    backend.ticks = ticks  # type: ignore[attr-defined]
    return time.process_time() - started, stepgen.state.motion_time_s, backend


def rig_jobs(result: BenchResult, quick: bool) -> None:
    """The rig's raster and circles in process, about 4 s of motion each (1 s quick): CPU per
    block of the planner's pop side, the step generator and the backend (no line path), and
    per second of motion; the best of a few runs."""
    scale = 1 if quick else 4
    for job in (rig_raster(lines=4 * scale), rig_circles(turns=2 * scale)):
        blocks = len(job.path)
        runs = [execute(0.0, job) for _ in range(2 if quick else 3)]
        cpu_s, motion_s, _ = min(runs, key=lambda run: run[0])
        print(f"rig {job.name:8} {blocks / motion_s:6,.0f} blocks/s  "
              f"{cpu_s / blocks * 1e6:6.1f} µs per block  {cpu_s / motion_s:.4f} s/s")
        result.add("klipper", f"rig {job.name}", us_per_block=(cpu_s / blocks * 1e6, "µs"),
                   cpu_per_motion_s=(cpu_s / motion_s, "s/s"))


COLD_GAP_S = 0.065  # the server's tick gap on a cruise at a 0.2 s lead


def cold_ticks(result: BenchResult, quick: bool) -> None:
    """The rig's jobs ticked back to back, then ``COLD_GAP_S`` apart: CPU per second of
    motion of the same work, and the ratio (the cost of waking cold)."""
    scale = 1 if quick else 2
    for job in (rig_long_moves(count=2 * scale), rig_circles(turns=scale),
                rig_raster(lines=2 * scale)):
        warm_s, motion_s, backend = min((execute(0.0, job) for _ in range(2)),
                                        key=lambda r: r[0])
        cold_s = execute(0.0, job, COLD_GAP_S)[0]
        samples_s = backend.ticks / motion_s  # type: ignore[attr-defined]
        print(f"rig {job.name:10} {samples_s:4.1f} samples/s, back to back "
              f"{warm_s / motion_s:.4f} s/s, {COLD_GAP_S * 1e3:.0f} ms apart "
              f"{cold_s / motion_s:.4f} s/s ({cold_s / warm_s:.1f}x)")
        result.add("klipper", f"rig {job.name} cold ticks",
                   warm_cpu_per_motion_s=(warm_s / motion_s, "s/s"),
                   cold_cpu_per_motion_s=(cold_s / motion_s, "s/s"),
                   cold_over_warm=(cold_s / warm_s, "x"), samples_per_s=(samples_s, "/s"))


def run(quick: bool) -> BenchResult:
    result = BenchResult("klipper-host", quick)
    rig_jobs(result, quick)
    cold_ticks(result, quick)
    cpu_s, motion_s, backend = execute(1.0 if quick else 4.0)
    wire = backend.mcu.link  # type: ignore[union-attr]
    assert isinstance(wire, WireCount)
    segments = float(backend.segments)  # type: ignore[attr-defined]
    errors_us = np.concatenate(backend.errors or [np.zeros(1)]) / CLOCK_HZ * 1e6
    bytes_s = wire.bytes / motion_s
    print(f"raster {segments / motion_s:,.0f} segments/s over {motion_s:.2f} s of motion")
    print(f"host CPU per second of motion   {cpu_s / motion_s:8.3f} s/s")
    print(f"bytes on the wire               {bytes_s:8,.0f} B/s "
          f"({bytes_s / BAUD_BYTES_S:.0%} of 250,000 baud)")
    print(f"blocks, messages per second     {wire.blocks / motion_s:8,.0f} "
          f"{wire.messages / motion_s:8,.0f}")
    pcts = np.percentile(errors_us, [50, 90, 99, 100])
    print("step error (µs early)           p50 {:.1f}  p90 {:.1f}  p99 {:.1f}  max {:.1f}".format(
        *pcts))
    result.add("klipper", "raster", segments_per_s=(segments / motion_s, "segments/s"),
               cpu_per_motion_s=(cpu_s / motion_s, "s/s"), wire_bytes_s=(bytes_s, "B/s"),
               wire_blocks_s=(wire.blocks / motion_s, "blocks/s"),
               link_share=(bytes_s / BAUD_BYTES_S, "x"),
               error_p50=(float(pcts[0]), "µs"), error_p99=(float(pcts[2]), "µs"),
               error_max=(float(pcts[3]), "µs"))
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__ or ""))
