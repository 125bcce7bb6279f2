"""The jobs of ``python -m benchmarks klipper``, written for each host, with what they should do.

Every job starts at rest at its ``start`` (reached before the measurement starts), runs at
F6000 (100 mm/s) and is the same motion for both hosts: motiond's Grbl G-code, and Klipper's
(``SET_PIN`` for the laser, which klippy times with the moves). Where a job's moves run from
rest to rest or corner to corner along one axis, its ``moves`` give each axis' trapezoids in
order: the ideal profile its steps are held against (both hosts limit a corner's speed by the
same junction deviation formula, and a reversal stops both).

* raster: lines of 0.1 mm segments along X, the laser (PB4) on along each line, off for the
  0.1 mm step over in Y (square corners at 6.95 mm/s);
* circles: 0.5 mm chords around a circle of 8 mm radius, the laser on (no ideal profile: the
  hosts' cornering differs in how it rounds each chord's junction, so only counts are held);
* long moves: 100 mm along X and back at 100 mm/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from benchmarks.klipper_rig_analysis import Trapezoid
from benchmarks.klipper_rig_hosts import (
    ACCEL_MM_S2,
    JUNCTION_DEVIATION_MM,
    LASER_S_MAX,
    STEPS_PER_MM,
)

FEED_MM_MIN = 6000.0
SPEED_MM_S = FEED_MM_MIN / 60
LASER = 0.8  # of full power on the raster's lines
SIN_HALF = math.sqrt(0.5)  # a square corner: v² = a·δ·sin(θ/2)/(1 - sin(θ/2)), both hosts
CORNER_MM_S = math.sqrt(ACCEL_MM_S2 * JUNCTION_DEVIATION_MM * SIN_HALF / (1 - SIN_HALF))


@dataclass
class Job:
    name: str
    start: tuple[float, float]
    end: tuple[float, float]
    motiond: list[str] = field(default_factory=list)
    klippy: list[str] = field(default_factory=list)
    path: list[tuple[float, float]] = field(default_factory=list)  # every point, in order
    moves: dict[str, list[Trapezoid]] = field(default_factory=dict)  # axis: its moves in turn
    order: list[str] = field(default_factory=list)  # which axis moves, move after move
    idle_s: float = 0.0  # the idle job: this long with nothing to do

    def steps(self, axis: int) -> tuple[int, int]:
        """(gross, net) steps the path makes on an axis (step at each half-step crossing)."""
        points = [self.start, *self.path]
        positions = [math.floor(p[axis] * STEPS_PER_MM + 0.5) for p in points]
        gross = sum(abs(b - a) for a, b in zip(positions, positions[1:], strict=False))
        return gross, positions[-1] - positions[0]

    def move_starts_s(self) -> dict[str, list[float]]:
        """When each axis' moves start on the job's ideal timeline (the moves back to back)."""
        starts: dict[str, list[float]] = {axis: [] for axis in self.moves}
        taken = dict.fromkeys(self.moves, 0)
        now_s = 0.0
        for axis in self.order:
            starts[axis].append(now_s)
            now_s += self.moves[axis][taken[axis]].duration_s
            taken[axis] += 1
        return starts

    def lines(self, host: str) -> list[str]:
        return self.motiond if host == "motiond" else self.klippy


def laser_lines(on: bool) -> tuple[str, str]:
    """(motiond's S word, klippy's SET_PIN line)."""
    value = LASER if on else 0.0
    return f"S{value * LASER_S_MAX:.0f}", f"SET_PIN PIN=laser VALUE={value:.2f}"


def raster(lines: int = 12, length_mm: float = 20.0, segment_mm: float = 0.1) -> Job:
    start = (10.0, 10.0)
    job = Job("raster", start, start, moves={"x": [], "y": []})
    job.motiond.append(f"M3 S0 F{FEED_MM_MIN:.0f}")
    job.klippy.append(f"G1 F{FEED_MM_MIN:.0f}")
    x, y = start
    per_line = round(length_mm / segment_mm)
    for line in range(lines):
        direction = 1 if line % 2 == 0 else -1
        s_on, pin_on = laser_lines(True)
        s_off, pin_off = laser_lines(False)
        job.klippy.append(pin_on)
        for k in range(per_line):
            x = start[0] + (k + 1) * segment_mm if direction > 0 else \
                start[0] + length_mm - (k + 1) * segment_mm
            job.motiond.append(f"G1 X{x:.3f}" + (f" {s_on}" if k == 0 else ""))
            job.klippy.append(f"G1 X{x:.3f}")
            job.path.append((x, y))
        job.moves["x"].append(Trapezoid(length_mm, SPEED_MM_S, ACCEL_MM_S2,
                                        CORNER_MM_S if line else 0.0, CORNER_MM_S))
        job.order.append("x")
        y += 0.1
        job.motiond.append(f"G1 Y{y:.3f} {s_off}")
        job.klippy += [pin_off, f"G1 Y{y:.3f}"]
        job.path.append((x, y))
        job.moves["y"].append(Trapezoid(0.1, SPEED_MM_S, ACCEL_MM_S2, CORNER_MM_S,
                                        CORNER_MM_S if line < lines - 1 else 0.0))
        job.order.append("y")
    job.motiond.append("M5")
    job.end = (x, y)
    return job


def circles(turns: int = 5, radius_mm: float = 8.0, chord_mm: float = 0.5) -> Job:
    center = (50.0, 50.0)
    start = (center[0] + radius_mm, center[1])
    job = Job("circles", start, start)
    count = round(2 * math.pi * radius_mm / chord_mm)
    s_on, pin_on = laser_lines(True)
    job.motiond.append(f"M3 {s_on} F{FEED_MM_MIN:.0f}")
    job.klippy += [f"G1 F{FEED_MM_MIN:.0f}", pin_on]
    for k in range(1, turns * count + 1):
        angle = 2 * math.pi * k / count
        x, y = (round(center[0] + radius_mm * math.cos(angle), 3),
                round(center[1] + radius_mm * math.sin(angle), 3))
        job.motiond.append(f"G1 X{x:.3f} Y{y:.3f}")
        job.klippy.append(f"G1 X{x:.3f} Y{y:.3f}")
        job.path.append((x, y))
    job.motiond.append("M5")
    job.klippy.append(laser_lines(False)[1])
    job.end = job.path[-1]
    return job


def long_moves(count: int = 4, length_mm: float = 100.0) -> Job:
    start = (10.0, 150.0)
    job = Job("long moves", start, start, moves={"x": [], "y": []})
    job.motiond.append(f"G1 F{FEED_MM_MIN:.0f}")
    job.klippy.append(f"G1 F{FEED_MM_MIN:.0f}")
    x = start[0]
    for k in range(count):
        x = start[0] + (length_mm if k % 2 == 0 else 0.0)
        job.motiond.append(f"G1 X{x:.3f}")
        job.klippy.append(f"G1 X{x:.3f}")
        job.path.append((x, start[1]))
        job.moves["x"].append(Trapezoid(length_mm, SPEED_MM_S, ACCEL_MM_S2))
        job.order.append("x")
    job.end = (x, start[1])
    return job


def idle(seconds: float = 5.0) -> Job:
    return Job("idle", (10.0, 10.0), (10.0, 10.0), idle_s=seconds)


def jobs(quick: bool) -> list[Job]:
    if quick:
        return [raster(lines=4), circles(turns=2), long_moves(count=2), idle(2.0)]
    return [raster(), circles(), long_moves(), idle()]
