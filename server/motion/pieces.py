"""The trajectory as constant-acceleration pieces, for backends that time their own steps.

Pure (no asyncio, no I/O). The step generator advances on a fixed-rate tick; a backend such as
a Klipper MCU needs the exact path between ticks to compute every step's time. The
:class:`PieceReporter` tells it each :class:`~server.motion.backend.Piece` (start time,
duration, start position, unit vector, start speed, acceleration) as the step generator takes a
block (its three phases), as a feed hold decelerates (each tick's deceleration, split exactly
at block boundaries) and when motion stops at once (a zero-length piece that cuts the rest).
Where an output follows motion (a laser whose power the backend times), ``power_of`` gives each
block's :class:`~server.motion.backend.PowerLaw`, evaluated as the block is taken (after its
ordered actions, M221 among them); a feed hold's pieces carry none (the tool is off).

A cruise continued by blocks that are all cruise, or a ramp continued by blocks that are all
one ramp at the same acceleration from the speed it reached, along the same direction from
where it ends, at the same power, at the time it ends, without ordered actions (a raster's
line of short segments: its ramp up, its cruise, its ramp down), is one piece, not one a
block: it stays open, and those blocks only lengthen it. The backend is told the open piece
as it stands (:meth:`PieceReporter.flush`: a piece from the same start, longer, which replaces
the shorter one) before anything may read it: the step generator flushes before each sample,
before a block's ordered actions and before it goes idle; a hold or a stop flushes first and
closes it.
Units: seconds on the kernel's clock, mm, mm/s, mm/s².
"""

from __future__ import annotations

import math
from collections.abc import Callable

from server.motion.backend import Backend, Piece, PowerLaw
from server.motion.moves import Move, Position
from server.motion.planner import Block
from server.motion.planner_intake import Geometry

PowerOf = Callable[[Move, float], PowerLaw | None]
"""A block's tool power from its move and nominal speed (mm/s); None: off."""
JOIN_S = 1e-9
"""A block that starts this close to the open piece's end continues it (float rounding of the
step generator's timeline, give or take a few units in the last place of the clock's seconds:
a host up for months counts them in units over 1 ns; any real gap opens a new piece), and a
phase this short at the end of a block (or at either end of a cruise block) is part of the
phase beside it (the planner's rounding of a junction speed to within 1e-14 of the cruise):
it moves the tool less than 1e-15 mm differently."""
SAME_ACCEL = 1e-9
"""Ramps whose accelerations differ by this share at most are one ramp (the planner computes
each block's from its speeds and duration: they differ in the last bits)."""
SAME_SPEED_MM_S = 1e-9
"""A ramp continues one that reaches its entry speed within this (float rounding)."""


class PieceReporter:
    """Reports the trajectory to ``backend.trajectory``; see the module docstring."""

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self.power_of: PowerOf | None = None
        self._run: Piece | None = None  # the open piece, as the backend was last told it
        self._run_s = 0.0  # its duration with the blocks that continued it since
        self._run_end_mm: Position = ()  # where the last block it covers ends
        self.lengthening = False
        """Whether the last block lengthened the open piece: such blocks come in runs (a
        raster's line), where :meth:`lengthen` takes the rest at once."""

    def block(self, start_s: float, block: Block) -> None:
        """A block's three phases, starting at ``start_s`` (or the open piece lengthened)."""
        if block.move is None or block.length_mm <= 0.0:
            return
        entry, cruise, t1, t2 = block.entry_mm_s, block.cruise_mm_s, block.accel_s, block.cruise_s
        t3 = block.decel_s
        power = None if self.power_of is None else self.power_of(block.move, block.nominal_mm_s)
        run = self._run
        if run is not None:
            if (not block.actions and block.start_mm == self._run_end_mm
                    and block.unit == run.unit and (power is run.power or power == run.power)
                    and abs(start_s - run.start_s - self._run_s) <= JOIN_S + 8 * math.ulp(start_s)
                    and self._continues(run, block)):
                self._run_s += t1 + t2 + t3
                self._run_end_mm = block.end_mm
                self.lengthening = True
                return
            if self._run_s != run.duration_s:  # (_close, without a call for nothing to tell)
                self.flush()
            self._run = None
        self.lengthening = False
        d1 = 0.5 * t1 * (entry + cruise)
        if t1 > 0.0:
            if t2 <= JOIN_S and t3 <= JOIN_S:  # a ramp to the end: blocks continuing it
                self._open(self._piece(start_s, t1 + t2 + t3, block, 0.0, entry,
                                       (cruise - entry) / t1, power), block)
                return
            self._piece(start_s, t1, block, 0.0, entry, (cruise - entry) / t1, power)
        if t2 > 0.0 and t3 <= JOIN_S:  # a cruise to the end: blocks continuing it lengthen it
            self._open(self._piece(start_s + t1, t2 + t3, block, d1, cruise, 0.0, power), block)
            return
        if t2 > 0.0:
            self._piece(start_s + t1, t2, block, d1, cruise, 0.0, power)
        if t3 > 0.0:
            self._open(self._piece(start_s + t1 + t2, t3, block, d1 + cruise * t2, cruise,
                                   (block.exit_mm_s - cruise) / t3, power), block)

    def lengthen(self, now_s: float, left_s: float, rows: list[list[float]],
                 geometry: list[Geometry]) -> tuple[int, float]:
        """How many of the blocks given by ``rows`` and ``geometry`` (the planner's
        :meth:`~server.motion.planner.Planner.final_rows`: the first starting ``left_s``
        before ``now_s``, each the next) only lengthen the open piece and end by ``now_s``;
        the piece is lengthened by them. Returns their count and ``left_s`` less their
        durations: what as many :meth:`block` calls would do, without a block object each
        (a raster's line is hundreds of such blocks)."""
        run = self._run
        if run is None:
            return 0, left_s
        power_of, unit, power = self.power_of, run.unit, run.power
        run_s, end_mm, count = self._run_s, self._run_end_mm, 0
        for ((length, _, _, _, _, _, nominal, _, entry, cruise, exit_, t1, t2, t3, duration),
             (move, actions, start, end, block_unit)) in zip(rows, geometry, strict=True):
            if (left_s < duration or move is None or length <= 0.0 or actions
                    or start != end_mm or block_unit != unit):
                break
            law = None if power_of is None else power_of(move, nominal)
            start_s = now_s - left_s
            if not ((law is power or law == power)
                    and abs(start_s - run.start_s - run_s) <= JOIN_S + 8 * math.ulp(start_s)
                    and _carries_on(run, run_s, entry, cruise, exit_, t1, t2, t3)):
                break
            run_s += t1 + t2 + t3
            end_mm = end
            left_s -= duration
            count += 1
        self._run_s, self._run_end_mm = run_s, end_mm
        return count, left_s

    def _open(self, piece: Piece, block: Block) -> None:
        """``piece`` runs to the end of ``block``: blocks that continue it lengthen it."""
        self._run, self._run_s, self._run_end_mm = piece, piece.duration_s, block.end_mm

    def _continues(self, run: Piece, block: Block) -> bool:
        """Whether ``block``'s motion is ``run``'s carried on (:func:`_carries_on`)."""
        return _carries_on(run, self._run_s, block.entry_mm_s, block.cruise_mm_s,
                           block.exit_mm_s, block.accel_s, block.cruise_s, block.decel_s)

    def flush(self) -> None:
        """Tell the backend the open piece as it stands, if blocks lengthened it since."""
        run = self._run
        if run is not None and self._run_s != run.duration_s:
            run = self._run = run.lasting(self._run_s)
            self.backend.trajectory(run)

    def _close(self) -> None:
        """The open cruise as it stands, and no more blocks lengthen it."""
        self.flush()
        self._run = None

    def hold(self, block: Block | None, distance_mm: float, tick_s: float, v: float, a: float,
             used_s: float) -> None:
        """A hold's deceleration this tick (from ``tick_s``, ``distance_mm`` into ``block``, at
        ``v`` slowing by ``a`` for ``used_s``) within the current block; it replaces the rest of
        the block's pieces from the tick on."""
        self._close()
        if block is None or block.move is None:
            return
        d0 = min(distance_mm, block.length_mm)
        if not used_s:
            self._piece(tick_s, 0.0, block, d0, 0.0, 0.0)
            return
        end_mm = d0 + v * used_s - 0.5 * a * used_s * used_s
        overflow = end_mm - block.length_mm
        inside_s = used_s - back_s(v - a * used_s, a, overflow) if overflow > 0.0 else used_s
        self._piece(tick_s, inside_s, block, d0, v, -a)

    def hold_into(self, block: Block, tick_s: float, overflow: float, v: float, a: float,
                  used_s: float) -> None:
        """The part of this tick's deceleration that ran ``overflow`` mm into ``block``."""
        self._close()
        if block.move is None or not used_s:
            return
        end_s = tick_s + used_s
        v_end = v - a * used_s
        into_s = back_s(v_end, a, overflow)
        beyond_s = back_s(v_end, a, overflow - block.length_mm) if (
            overflow > block.length_mm) else 0.0
        self._piece(end_s - into_s, into_s - beyond_s, block, 0.0, v_end + a * into_s, -a)

    def stop(self, tick_s: float, position_mm: Position) -> None:
        """Motion stopped at once at ``position_mm``: what was reported after it is dropped."""
        self._close()
        zeros = tuple(0.0 for _ in position_mm)
        self.backend.trajectory(Piece(tick_s, 0.0, position_mm, zeros, 0.0, 0.0))

    def _piece(self, start_s: float, duration_s: float, block: Block, from_mm: float,
               speed_mm_s: float, accel_mm_s2: float, power: PowerLaw | None = None) -> Piece:
        start = block.start_mm if from_mm == 0.0 else tuple(
            p + u * from_mm for p, u in zip(block.start_mm, block.unit, strict=True))
        piece = Piece(start_s, duration_s, start, block.unit, speed_mm_s, accel_mm_s2, power)
        self.backend.trajectory(piece)
        return piece


def back_s(v_end: float, a: float, distance_mm: float) -> float:
    """Seconds before reaching ``v_end`` (decelerating at ``a``) that ``distance_mm`` remained."""
    if distance_mm <= 0.0:
        return 0.0
    return 2.0 * distance_mm / (v_end + math.sqrt(v_end * v_end + 2.0 * a * distance_mm))


def _carries_on(run: Piece, run_s: float, entry: float, cruise: float, exit_: float,
                t1: float, t2: float, t3: float) -> bool:
    """Whether a block of these speeds and phase durations is ``run`` (``run_s`` long so far)
    carried on: a cruise at its speed, or one ramp at its acceleration from the speed it
    reaches (the other phases under ``JOIN_S``)."""
    a = run.accel_mm_s2
    if a == 0.0:
        return t1 <= JOIN_S and t3 <= JOIN_S and cruise == run.start_mm_s
    if t2 > JOIN_S:
        return False
    if t3 <= JOIN_S < t1:
        ramp_a, from_mm_s = (cruise - entry) / t1, entry
    elif t1 <= JOIN_S < t3:
        ramp_a, from_mm_s = (exit_ - cruise) / t3, cruise
    else:
        return False
    reached_mm_s = run.start_mm_s + a * run_s
    return (abs(ramp_a - a) <= SAME_ACCEL * abs(a)
            and abs(from_mm_s - reached_mm_s) <= SAME_SPEED_MM_S)
