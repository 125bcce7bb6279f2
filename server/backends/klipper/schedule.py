"""The Klipper backend's pieces and their step schedule: the trajectory in, ``queue_step`` out.

:class:`StepSchedule` is the part of :class:`~.backend.KlipperBackend` (a base class of it) that
turns the trajectory into the MCU's step messages. The step generator tells the backend every
constant-acceleration piece of the trajectory (:meth:`StepSchedule.trajectory`); at each sample,
up to its time, each axis' stretches of the pieces (:mod:`.steptimes`) go to its compiled step
axis (``_stepaxis.c``), which solves their exact step times, mapped to MCU ticks at ``t +
lead_time_s`` in the MCU's own time base (:mod:`.printclock`: the nominal ``CLOCK_FREQ``; the
fitted clock of :mod:`.clocksync` anchors the schedule's start and sets the host's deadlines),
holds them, and compresses what is due into ``queue_step`` runs within ``max_error_s``
(:mod:`.stepcompress`), with ``set_next_step_dir`` on direction changes and
``reset_step_clock`` after a long idle or a reconfiguration. A run that
may still grow is held back at most all of the lead but ``RIDE_THROUGH_S`` (at least a quarter
of it, ``HOLD_BACK_SHARE``), so a host stall of up to ``lead_time_s`` - hold-back - ``flush_s``
(130 ms with a lead of 0.2 s or more) never starves the MCU. Messages leave in order while the
MCU's move queue (``move_count`` from its config) has room (:mod:`.movequeue`), in bursts that
the link packs into as few message blocks as fit; messages that would only part-fill a burst's
last block wait for more while none of them is due within ``lead_time_s`` - ``hold_back_s``
and the share (as a held-back run does), so blocks leave fuller; a sample sends what would
turn within ``SHARE_OF_HOLD_BACK`` of the hold-back after it (the share: at least a flush),
so the next sample comes no sooner and turns close together take one wake-up. The motion's
timeline maps to the MCU's clock here too (:meth:`StepSchedule._scheduled_clock`), for the
outputs (:mod:`.outputs`).

Kept apart from the outputs and the board's session (:mod:`.session`) so that the work done per
piece and per sample reads in one place. As a base class its methods are the backend's own (no
call goes through another object); its state is the backend's, created by
``KlipperBackend.__init__``.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import TYPE_CHECKING

from server.backends.klipper.mcu import KlipperFault, Mcu
from server.backends.klipper.movequeue import MoveQueue
from server.backends.klipper.pins import Axis, Output
from server.backends.klipper.printclock import PrintClock
from server.backends.klipper.stepcore import StepAxis, off_track, piece_steps
from server.backends.klipper.steptimes import FloatArray, step_target
from server.backends.klipper.trail import Trail
from server.motion.backend import Piece

if TYPE_CHECKING:
    from server.config import BackendConfig

log = logging.getLogger("motiond.klipper")
REST_S = 0.05
"""A pause in sampling longer than this is a rest (the schedule may start afresh)."""
RIDE_THROUGH_S = 0.15
"""A run that may still grow is sent at the latest this long before its first step is due
(less a flush: the host stall every step survives, 130 ms); the rest of the lead is how long
it may wait to grow (the hold-back: 150 ms at the default 0.3 s lead). A longer lead buys
longer runs, fewer bytes, and a slower feed hold."""
HOLD_BACK_SHARE = 0.25
"""With a short lead the hold-back is at least this share of it (50 ms at 0.2 s: 130 ms of
ride-through still)."""
AHEAD_MAX_S = 0.01
"""The most the board's clock may run ahead of the schedule as fitted (or a tenth of the
lead; the lead, and the stall the MCU rides through, shrink by as much) before the schedule
is steered back (:mod:`.printclock`)."""
BEHIND_MAX_S = 0.05
"""The most it may fall behind (or a quarter of the lead: the lead grows by as much)."""
SHARE_OF_HOLD_BACK = 0.5
"""What turns within this share of the hold-back after a sample (75 ms at the default lead; at
least a flush) leaves at it, so the next sample comes no sooner: a wake-up of the host costs
more (0.3-0.6 ms of CPU on a shared 2-core VM, several times that on a small board computer)
than what sending early costs on the wire (a run cut: a message of a few bytes; a block
part-filled: its 5). Runs still grow for the rest of the hold-back."""
SLICE_END_S = 1e-6  # a sample this little past the last piece's end is a late tick's slice


def _lengthens(piece: Piece, before: Piece) -> bool:
    """Whether ``piece`` is ``before`` told again, longer (blocks that continue a run lengthen
    it: :meth:`~server.motion.pieces.PieceReporter.flush`): the same motion from the same
    start, so nothing that happens where a piece starts (the followed output turned on or off,
    the motors enabled, a rebase) happens again."""
    return (piece.start_s == before.start_s and piece.duration_s >= before.duration_s
            and piece.start_mm == before.start_mm and piece.unit == before.unit
            and piece.start_mm_s == before.start_mm_s
            and piece.accel_mm_s2 == before.accel_mm_s2 and piece.power == before.power)


class StepSchedule:
    """The pieces and their steps; see the module docstring."""

    # The backend's state this part reads and writes (set by KlipperBackend.__init__).
    cfg: BackendConfig
    lead_s: float
    hold_back_s: float
    flush_s: float
    axes: list[Axis]
    _steps: tuple[StepAxis, ...]  # each axis' (Axis.steps), for the compiled calls
    outputs: dict[str, Output]
    errors: list[memoryview] | None
    mcu: Mcu | None
    ready: bool
    fault: str | None
    motors_on: bool
    _enable_clock: int
    _motors_off_s: float
    _pieces: deque[Piece]
    _motion_end_s: float
    _trail: Trail
    _head: Piece | None
    _sample_s: float | None
    _follow: Output | None
    _follow_on: bool
    _generated_s: float
    _queue: MoveQueue
    _print: PrintClock

    if TYPE_CHECKING:
        def halt(self) -> None: ...  # the session's
        def _on_fault(self, reason: str) -> None: ...
        def _follow_piece(self, piece: Piece, rel_s: float, first: bool) -> None: ...  # outputs'
        def _set_followed(self, value: float, when_s: float, top: int) -> None: ...
        def _level_top(self, out: Output) -> int: ...
        def _switch_motors(self, enabled: bool, clock: int) -> None: ...

    def trajectory(self, piece: Piece) -> None:
        if piece.duration_s > 0.0 and not self.ready:
            raise KlipperFault(self.fault or f"the MCU on {self.cfg.serial} is not ready")
        if piece.duration_s > 0.0:
            self._motion_end_s = piece.start_s + piece.duration_s
        else:
            self._motion_end_s = min(self._motion_end_s, piece.start_s)
        pieces = self._pieces
        if not pieces or pieces[-1].start_s + pieces[-1].duration_s > piece.start_s:
            self._replace_from(piece.start_s)  # (else it follows on: nothing to cut)
        if piece.duration_s > 0.0:
            pieces.append(piece)

    def _replace_from(self, start_s: float) -> None:
        """What the pieces and the trail held from ``start_s`` on is replaced: cut there."""
        pieces = self._pieces
        while pieces and pieces[-1].start_s >= start_s:
            pieces.pop()
        if pieces and pieces[-1].start_s + pieces[-1].duration_s > start_s:
            last = pieces.pop()
            cut = last.lasting(start_s - last.start_s)
            pieces.append(cut)
            if last is self._head:
                self._head = cut
        self._trail.cut(start_s)  # (it ends where the pieces left start)

    def _when_s(self, time_s: float) -> float:
        """When a change asked for at ``time_s`` (on the motion's timeline: a block's start
        for its actions) happens: then, or at the last sample if that is later; at ``time_s``
        after a rest (the schedule starts afresh)."""
        if self._rested(time_s):
            self._print.unanchor()  # anchored afresh at the live fit
            return time_s
        return time_s if self._sample_s is None else max(time_s, self._sample_s)

    def _rested(self, time_s: float) -> bool:
        """Whether the step generator slept since the last sample with nothing queued, moving
        or on: the schedule may then start afresh from the live clock fit (a host stall in
        motion is no rest: its schedule stays continuous)."""
        sample_s = self._sample_s
        return (sample_s is None or time_s - sample_s > REST_S) and not (
            self._pieces or self._queue.waiting or self._busy())

    def _scheduled_clock(self, when_s: float) -> int:
        """The MCU clock at which what the machine does at ``when_s`` happens."""
        if not self._print.anchored:  # just (re)configured: no step has set the map yet
            self._update_map(when_s + self.lead_s)
        return int(self._motion_clock(when_s + self.lead_s))

    # -- steps --------------------------------------------------------------------------------
    def _clock_at(self, host_s: float) -> float:
        """The fitted (live) MCU clock at host time ``host_s``: deadlines, flow control."""
        assert self.mcu is not None and self.mcu.clock is not None
        return self.mcu.clock.clock_at(host_s)

    def _motion_clock(self, print_s: float | FloatArray) -> float | FloatArray:
        """The MCU clock scheduled for print time ``print_s`` (kernel time + the lead)."""
        return self._print.clock(print_s)

    def _update_map(self, frontier_s: float) -> None:
        """Anchor the schedule to the fit while nothing is scheduled (a jump then moves no
        step), else steer it from ``frontier_s`` (the latest time steps were scheduled for)."""
        assert self.mcu is not None and self.mcu.clock is not None
        fit = self.mcu.clock
        if not self._print.anchored or self._schedule_idle():
            self._print.nominal_hz = fit.nominal_hz  # the dictionary's CLOCK_FREQ
            self._print.anchor(frontier_s, fit.clock_at(frontier_s))
        else:
            self._print.steer(frontier_s, fit.clock_at(frontier_s))

    def _schedule_idle(self) -> bool:
        """Nothing waits to be scheduled or sent, and every step sent is already past."""
        if self._pieces or self._queue.waiting or any(a.steps.held for a in self.axes):
            return False
        now = self._now_clock()
        return all(a.steps.last_clock < now for a in self.axes) and all(
            o.last_clock < now for o in self.outputs.values()) and self._enable_clock < now

    def _now_clock(self) -> float:
        return self._clock_at(time.monotonic())

    def _generate(self, until_s: float) -> None:
        """Exact step clocks of every axis (and the followed output's power) for the
        trajectory up to ``until_s``."""
        pieces = self._pieces
        while pieces:
            piece = pieces[0]
            end_s = min(until_s, piece.start_s + piece.duration_s)
            rel_s = end_s - piece.start_s
            if rel_s < 0.0:
                break
            self._piece_steps(piece, rel_s)
            if end_s < piece.start_s + piece.duration_s:
                break
            pieces.popleft()
            self._generated_s = end_s
        print_clock = self._print  # solved as _motion_clock maps them
        for steps in self._steps:
            steps.add(print_clock.ref_clock, print_clock.hz, print_clock.ref_s)
        out = self._follow
        if (self._follow_on and out is not None and not pieces
                and until_s > self._generated_s + SLICE_END_S):
            self._follow_on = False  # motion ended (not merely a slice of a late tick)
            self._set_followed(0.0, self._generated_s, self._level_top(out))

    def _piece_steps(self, piece: Piece, rel_s: float) -> None:
        """Each axis' whole steps along ``piece`` up to ``rel_s`` into it, queued on its step
        axis (solved together at the end of the sample: ``_stepaxis.c``)."""
        before = self._head
        first = piece is not before
        if first and before is not None and piece.start_s == before.start_s and _lengthens(
                piece, before):
            self._head = piece  # the same motion carried on (a run of blocks: see pieces.py):
            self._trail.add(piece)  # steps and the followed output go on where they were
            first = False
        elif first:  # first look at this piece
            self._head = piece
            self._trail.add(piece)
            # the pieces of one block share its direction (the same tuple) and follow on from
            # each other: only the first of a block may start elsewhere
            if ((before is None or piece.unit is not before.unit)
                    and off_track(self._steps, piece.start_mm) and self._rebased(piece)):
                return
            if (not self.motors_on and piece.duration_s > 0.0
                    and piece.start_s >= self._motors_off_s):  # enabled as it starts
                self._switch_motors(True, int(self._motion_clock(piece.start_s + self.lead_s)))
        if self._follow is not None:
            self._follow_piece(piece, rel_s, first)
        if rel_s != 0.0:
            piece_steps(self._steps, piece.start_mm, piece.unit, piece.start_mm_s,
                        piece.accel_mm_s2, rel_s, piece.start_s + self.lead_s)

    def _rebased(self, piece: Piece) -> bool:
        """A piece that starts away from where the steps are (the position was redefined,
        as homing does: ``off_track``) moves the step count there without stepping."""
        jumped = False
        for axis, start in zip(self.axes, piece.start_mm, strict=True):
            here = start * axis.steps_per_mm
            if abs(here - axis.position) > 1.0:
                log.warning("axis %s redefined at %.3f mm: no steps sent", axis.name, start)
                axis.position = step_target(here)
                jumped = True
        return jumped and piece.duration_s == 0.0

    @property
    def _send_ahead_s(self) -> float:
        """What is due within this of a sample leaves at it: the lead less the hold-back,
        and the share more (what would turn within ``SHARE_OF_HOLD_BACK`` of the hold-back,
        and at least before another flush could come, goes with it: a run of another axis, a
        message held to share a block), so that one sample serves the turns that come close
        together."""
        share_s = max(self.flush_s, SHARE_OF_HOLD_BACK * self.hold_back_s)
        return self.lead_s - self.hold_back_s + share_s

    def _flush(self, now_s: float) -> None:
        """Compress what is due soon (all of it when motion has no more pieces): steps that
        may still join a longer run wait until their first is due within ``_send_ahead_s``
        (compressed once then, not at every flush). Of those, the runs complete
        before the last step known go; the last run waits on while its own first step is not
        yet due, so that it grows (a cruise is not cut where an acceleration's steps were
        sent). Motion has ended once the samples pass the last piece's end (a late tick's
        slice ends exactly on one)."""
        idle = not self._pieces and now_s > self._generated_s + SLICE_END_S
        force_clock = float(self._motion_clock(now_s + self._send_ahead_s))
        messages: list[tuple[bytes, int | None, int]] = []
        for axis in self.axes:  # compressed and encoded there (_stepaxis.c)
            axis.steps.flush(force_clock, idle, messages, self.errors)
        if messages:
            self._queue.extend(messages)

    def _pump(self) -> None:
        """Send queued messages in order while the MCU's move queue has room. Less than a
        block of messages all due later than a sample must send (``_send_ahead_s`` ahead)
        waits for more, at flushes and between them alike, so they share blocks; a message so
        held still leaves at least ``lead_s`` - ``hold_back_s`` - ``flush_s`` ahead, as a
        held-back run does."""
        mcu = self.mcu
        if mcu is None or not self._queue.waiting:
            return
        now = self._now_clock()
        hold_after = None
        if mcu.clock is not None:
            hold_after = now + self._send_ahead_s * mcu.clock.freq_hz
        late_ms = self._queue.pump(mcu, now, hold_after)
        if late_ms is not None:
            self.halt()
            self._on_fault(f"steps due {late_ms:.1f} ms ago were not sent in time (host "
                           "stall or link too slow: raise lead_time_s)")

    def _busy(self) -> bool:
        """Whether the MCU may still have steps or an output on."""
        if self.mcu is None or self.mcu.clock is None or not self.ready:
            return False
        return (self._queue.busy(self._now_clock())
                or any(out.value > 0.0 for out in self.outputs.values()))

    def _drop_motion(self) -> None:
        self._motion_end_s = 0.0
        self._trail.clear()
        self._follow_on = False
        self._pieces.clear()
        self._queue.drop()
        for axis in self.axes:
            axis.steps.clear()
