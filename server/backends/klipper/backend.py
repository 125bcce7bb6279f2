"""``[backend] kind = "klipper"``: stock Klipper MCU firmware executes the step generator's steps.

:class:`KlipperBackend` is the :class:`~server.motion.backend.Backend` the machine drives. It
holds the backend's state and is composed of three parts, each a base class in a module of its
own whose methods run on the backend itself:

* :mod:`.schedule`: the pieces of the trajectory and their step schedule: ``queue_step`` runs
  timed in the MCU's clock a lead ahead, held back to grow, sent while the MCU has room;
* :mod:`.outputs`: outputs set on the motion's timeline, the laser's power following the
  pieces, the motors' enable pins, the refresh the firmware's watchdog needs;
* :mod:`.session`: the board's session: connecting and configuring it, faults, the emergency
  stop, and restarting a shut-down board (``$X``, M999).

The step generator tells this backend every constant-acceleration piece of the trajectory
(:meth:`~.schedule.StepSchedule.trajectory`) and how far its clock has reached
(:meth:`KlipperBackend.sample`, at the ticks: while motion runs, when
:meth:`KlipperBackend.next_sample_s` says, at least a ``flush_s``
(:attr:`KlipperBackend.tick_s`) and at most ``SAMPLE_GAP_MAX_S`` apart, since nothing here is
timed by the ticks). ``?`` reads where the board is from the pieces (:mod:`.trail`).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Callable, Sequence

from server.backends.klipper.mcu import KlipperFault, Mcu
from server.backends.klipper.movequeue import MoveQueue
from server.backends.klipper.outputs import OutputTiming
from server.backends.klipper.pins import Axis, Output
from server.backends.klipper.printclock import PrintClock
from server.backends.klipper.schedule import (
    AHEAD_MAX_S,
    BEHIND_MAX_S,
    HOLD_BACK_SHARE,
    RIDE_THROUGH_S,
    StepSchedule,
)
from server.backends.klipper.session import BoardSession
from server.backends.klipper.stepcore import StepAxis
from server.backends.klipper.trail import Trail
from server.config import CoreConfig
from server.motion.backend import Piece

log = logging.getLogger("motiond.klipper")
CONFIRM_S = 0.002  # a clock poll's round trip, about: the end of motion confirmed by one
TRAIL_EXTRA_S = 1.0  # the pieces are kept this long beyond the lead (where the tool was)
SAMPLE_MARGIN_S = 0.012  # a sample asked for at the last moment comes this much before it
# (a woken loop is late by a millisecond or so, and the sample works a few before it sends:
# 5 or 8 ms left runs 1-5 ms short of the ride-through on a slow shared VM)
SAMPLE_GAP_MAX_S = 0.17
"""The longest the samples may pause while steps or outputs are under way; within it, at
most the hold-back plus a flush (less ``SAMPLE_MARGIN_S``): what a sample does not yet
generate still leaves the ride-through the flushes kept (``lead_s`` - ``hold_back_s`` -
``flush_s``: 130 ms at the default lead), a run held back to grow leaves as late as the
flushes let it (runs as long: the same bytes), and a board's shutdown or fault mid-motion is
read (and alarmed) within it (158 ms at the default lead)."""


class KlipperBackend(BoardSession, OutputTiming, StepSchedule):
    """See the module docstring."""

    wants_trajectory = True

    def __init__(self, core: CoreConfig, *, record: bool = False, retry_s: float = 1.0,
                 flush_s: float = 0.02) -> None:
        cfg = core.backend
        assert cfg.serial is not None
        self.cfg, self.retry_s, self.flush_s = cfg, retry_s, flush_s
        self.lead_s = cfg.lead_time_s
        self.hold_back_s = max(HOLD_BACK_SHARE * self.lead_s, self.lead_s - RIDE_THROUGH_S)
        self.axis_names = core.axis_names
        self.axes = [Axis(n, a.steps_per_mm, steps=StepAxis(record=record))
                     for n, a in zip(core.axis_names, core.axes.values(), strict=True)]
        self._steps = tuple(axis.steps for axis in self.axes)
        self.outputs = {name: Output(name, out) for name, out in cfg.outputs.items()}
        self.values: dict[str, float] = {}
        self.motors_on, self._enable_clock = True, 0
        self._motors_off_s = 0.0  # the motion time the drivers were last turned off at
        self.pwm_log: list[tuple[float, str, float, int]] | None = [] if record else None
        self.errors: list[memoryview] | None = [] if record else None  # how early
        self.mcu: Mcu | None = None
        self.ready = False
        self.fault: str | None = None
        self._fault_to_raise: str | None = None
        self._pieces: deque[Piece] = deque()
        self._motion_end_s = 0.0  # where the trajectory given ends (kernel clock)
        # the pieces steps were generated from: the MCU is where they were a lead time ago
        self._trail = Trail(self.lead_s + TRAIL_EXTRA_S)
        self._head: Piece | None = None  # the piece steps are being generated from
        self._sample_s: float | None = None
        self._follow: Output | None = None  # the output timed from the pieces' power
        self._follow_period_s = 0.001
        self._follow_next_s = 0.0  # the next motion time the followed power is looked at
        self._follow_on = False  # the followed output is on because motion turned it on
        self._generated_s = 0.0  # where the last generated piece ended (kernel clock)
        self._queue = MoveQueue()
        self._print = PrintClock(0.0, min(AHEAD_MAX_S, 0.1 * self.lead_s),
                                 min(BEHIND_MAX_S, 0.25 * self.lead_s))
        self.identity: dict[str, str] = {}  # the board first served: another is refused
        self.shut_down = False  # the board is shut down until recover() restarts it
        self._recover = asyncio.Event()  # recover() asks the waiting run() to restart
        self._configured = asyncio.Event()  # ...which sets this once the board is ready
        self._config_base = [0] * len(self.axes)  # axis positions when the MCU was configured
        self.relocate: Callable[[Sequence[float]], None] = lambda _: None
        self._wake: Callable[[], None] = lambda: None

    blocks_per_call = 128
    """How many blocks one call of the step generator goes through before it slices the rest
    (see :mod:`server.motion.stepgen`): a sample covers up to ``SAMPLE_GAP_MAX_S`` of motion
    (a raster's 0.1 mm segments at 100 mm/s: about 80 blocks at 9 samples a second), whole in
    one call where 64 sliced it, each slice a sample of its own (the messages it sends
    forced out early); a raster's blocks mostly lengthen one piece (a few µs each)."""

    @property
    def tick_s(self) -> float:
        """The step generator ticks at most once a flush (less often while motion runs: see
        :meth:`next_sample_s`): steps, outputs and the followed output's power are timed from
        the pieces, not from the ticks."""
        return self.flush_s

    @property
    def ticks_when_idle(self) -> bool:
        """Whether the step generator must keep ticking while nothing moves: while steps or
        messages are queued, an output is on (it is refreshed from :meth:`sample`) or a fault
        waits to be raised. Otherwise it sleeps (an idle server costs next to no CPU)."""
        return (self._fault_to_raise is not None or bool(self._pieces)
                or bool(self._queue.waiting) or self._busy())

    def rest(self) -> None:
        """The machine's hook: the ticks stop (nothing to sample): the board's messages are
        read as they arrive again, so an idle board's shutdown or restart is seen at once."""
        if self.mcu is not None:
            self.mcu.link.rest()

    def wake_with(self, wake: Callable[[], None]) -> None:
        """The machine's hook: ``wake`` resumes ticks (a fault, an output switched on)."""
        self._wake = wake

    def watch_position(self, relocate: Callable[[Sequence[float]], None]) -> None:
        """The machine's hook: called with where the tool really stopped (mm) after a stop."""
        self.relocate = relocate

    # -- the Backend seam ---------------------------------------------------------------------
    @property
    def steps_per_mm(self) -> tuple[float, ...]:
        return tuple(a.steps_per_mm for a in self.axes)

    @steps_per_mm.setter
    def steps_per_mm(self, values: tuple[float, ...]) -> None:
        for axis, value in zip(self.axes, values, strict=True):
            axis.position = round(axis.position / axis.steps_per_mm * value)
            axis.steps_per_mm = value

    def step(self, time_s: float, delta_steps: object) -> None:
        """Whole steps per tick are not used: the exact times come from :meth:`trajectory`."""

    def sample(self, time_s: float, position_mm: object, speed_mm_s: float) -> None:
        if self.mcu is not None:
            self.mcu.link.sample()  # what the board sent since the last tick (see .link)
        if self._fault_to_raise is not None:
            message, self._fault_to_raise = self._fault_to_raise, None
            raise KlipperFault(message)
        if self._rested(time_s):
            self._print.unanchor()  # anchored afresh at the live fit
        self._sample_s = time_s
        if not self.ready:
            return
        self._update_map(time_s + self.lead_s)
        self._generate(time_s)
        self._refresh_outputs(time_s)
        self._flush(time_s)  # every sample is a flush (see tick_s)
        if self.mcu is not None:
            self.mcu.busy = self._busy()
        self._pump()

    def next_sample_s(self, time_s: float) -> float:
        """When the sample after the one at ``time_s`` is needed (the step generator ticks
        then, if that is later than its own next tick: every wake-up of the process costs
        CPU). A run that may still grow leaves at the first sample after its turn (see
        :meth:`_flush`): a sample is asked for just after it; the steps not yet generated
        must leave at least ``lead_s`` - ``hold_back_s`` ahead, and an output that is on is
        refreshed in time, and messages held to share a block leave at their turn (as late
        as a flush would send them), or as soon as the MCU's move queue has room for those
        waiting for it; at most ``SAMPLE_GAP_MAX_S`` apart. At once (the next tick) while a
        fault waits to be raised or the board is not ready."""
        mcu = self.mcu
        if (not self.ready or self._fault_to_raise is not None or not self._print.anchored
                or mcu is None or mcu.clock is None):
            return time_s
        late_s = self.flush_s - SAMPLE_MARGIN_S  # past a turn: as a flush would come
        soonest_s = time_s + min(SAMPLE_GAP_MAX_S, self.hold_back_s + late_s)
        freq_hz = mcu.clock.freq_hz
        turn = self._queue.turn(mcu.move_count, (self.lead_s - self.hold_back_s) * freq_hz,
                                freq_hz)
        if turn is not None:
            full = self._queue.full(mcu.move_count)
            soonest_s = min(soonest_s, mcu.clock.host_at(turn) + (0.0 if full else late_s))
        to_print = self._print.time_at
        for axis in self.axes:
            first = axis.steps.first_clock()  # what it holds waits for its turn (_flush)
            if first == 0.0:
                return time_s
            if first is not None:
                turn_s = to_print(first) - self.lead_s + self.hold_back_s
                soonest_s = min(soonest_s, turn_s + late_s)
        for out in self.outputs.values():
            if out.value > 0.0 and out.max_ticks:
                refresh_s = to_print(out.last_clock + out.max_ticks // 2) - self.lead_s
                soonest_s = min(soonest_s, refresh_s)
        return max(time_s, soonest_s)

    def declare_tool(self, name: str) -> None:
        if name not in self.outputs:
            log.warning("tool output %r is not in [backend.outputs]: it drives no pin", name)

    def output(self, name: str) -> float:
        return self.values.get(name, 0.0)

    def probe_triggered(self, position_mm: object) -> bool:
        return False

    def switch_triggered(self, name: str) -> bool:
        return False

    def place_switch(self, name: str, at_mm: float) -> None:
        pass

    def position_at_mm(self, time_s: float) -> tuple[float, ...] | None:
        """The planned position a lead time before ``time_s``: what the MCU has executed
        (the step schedule runs ``lead_s`` behind the step generator)."""
        if not self.ready:
            return None
        return self._trail.position_at(self._print_time_at(time_s) - self.lead_s)

    def speed_at_mm_s(self, time_s: float) -> float | None:
        """The path speed the MCU runs at at ``time_s`` (the plan a lead time before)."""
        if not self.ready or not len(self._trail):
            return None
        return self._trail.speed_at(self._print_time_at(time_s) - self.lead_s)

    def done_at_s(self) -> float:
        """The last step executes a lead time after the trajectory ends: when the clock fit
        puts the board's clock past it and a reading of that clock says so (the fit cannot
        see a board that lost time since its last reading). Until one does, a reading is
        asked for and the answer looked for ``CONFIRM_S`` later."""
        if not self.ready or not self._motion_end_s:
            return 0.0
        end_s = self._motion_end_s + self.lead_s
        mcu = self.mcu
        if mcu is None or mcu.clock is None or not self._print.anchored:
            return end_s  # nothing was scheduled on the board
        end_clock = float(self._print.clock(end_s))
        due_s, now_clock = mcu.clock.host_at(end_clock), self._now_clock()
        if mcu.clock.last_clock >= end_clock:  # a reading is past it: done
            return min(due_s, mcu.clock.host_at(now_clock))
        if now_clock < end_clock:
            return due_s
        mcu.poll_now()
        return mcu.clock.host_at(now_clock) + CONFIRM_S

    def _print_time_at(self, host_s: float) -> float:
        """The print time the MCU executes at host time ``host_s`` (through the fit)."""
        if self.mcu is None or self.mcu.clock is None or not self._print.anchored:
            return host_s
        return self._print.time_at(self.mcu.clock.clock_at(host_s))
