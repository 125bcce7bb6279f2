"""``[backend] kind = "klipper"``: stock Klipper MCU firmware executes the step generator's steps.

The step generator tells this backend every constant-acceleration piece of the trajectory
(:meth:`trajectory`) and how far its clock has reached (:meth:`sample`, at the ticks: while
motion runs, when :meth:`next_sample_s` says, at least a ``flush_s`` (:attr:`tick_s`) and at
most ``SAMPLE_GAP_MAX_S`` apart, since nothing here is timed by the ticks). Up to that time each
axis' exact step times are computed for all the pieces at once (:mod:`.steptimes`), mapped to
MCU ticks at
``t + lead_time_s`` in the MCU's own time base (:mod:`.printclock`: the nominal ``CLOCK_FREQ``;
the fitted clock of :mod:`.clocksync` anchors the schedule's start and sets the host's
deadlines), and compressed into
``queue_step`` runs within ``max_error_s`` (:mod:`.stepcompress`) every ``flush_s``, with
``set_next_step_dir`` on direction changes and ``reset_step_clock`` after a long idle or a
reconfiguration. A run that may still grow is held back at most all of the lead but
``RIDE_THROUGH_S`` (at least a quarter of it, ``HOLD_BACK_SHARE``), so a host stall of up to
``lead_time_s`` - hold-back - ``flush_s`` (130 ms with a lead of 0.2 s or more) never starves
the MCU. Messages leave in order while the MCU's move queue (``move_count`` from its config)
has room (:mod:`.movequeue`), in bursts that the link packs into as few message blocks as
fit; messages that would only part-fill a burst's last block wait for more while none of
them is due within ``lead_time_s`` - ``hold_back_s`` (as a held-back run does), so blocks
leave fuller.

Outputs named in ``[backend.outputs]`` become ``queue_pwm_out``/``queue_digital_out`` at the
MCU time of the motion time they are set for (a line's actions: its block's start; otherwise
the last sample) plus the lead, so they land on the steps they belong to. The laser's output
follows the pieces themselves (:meth:`follow_power`: each piece carries its power law): on and
off exactly where a piece starts, and along the speed on a 1 ms grid of motion time. An output
that is on is sent again every half ``max_duration_s``: the firmware's watchdog turns it off
when motiond stops doing so. ``?`` reads where the board is from the pieces (:mod:`.trail`).

Stopping: halt (alarm, M112, Ctrl-X) sends ``emergency_stop`` at once when the MCU has anything
queued or an output on, and so does every fault while the board can still hear. A shut-down
board stays so (the machine in ALARM, every move refused) until :meth:`recover` (``$X``, M999):
where each stepper stopped is read from the firmware first and becomes the machine position
(``relocate``), then the board is restarted (``restart_method``) and configured afresh. A
fault (:class:`~.mcu.KlipperFault`) is raised once from the next :meth:`sample`, which the
machine turns into an alarm; the backend then reconnects every ``retry_s``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from math import floor

from server.backends.klipper.codec import ProtocolError
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.mcu import (
    CONNECT_TIMEOUT_S,
    Command,
    KlipperFault,
    Mcu,
    McuShutdown,
    NeedsRestart,
)
from server.backends.klipper.movequeue import MoveQueue
from server.backends.klipper.pins import Axis, Output, config_commands
from server.backends.klipper.printclock import PrintClock
from server.backends.klipper.steptimes import FloatArray, Spans, step_target
from server.backends.klipper.trail import Trail
from server.config import CoreConfig
from server.errors import CommandError, Error
from server.motion.backend import Piece

log = logging.getLogger("motiond.klipper")
EXIT_GRACE_S = 0.3
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
RESTART_WAIT_S = 0.3  # a restarted board boots before it is asked who it is
RESTART_PATIENCE_S = 10.0  # a restarted board's first answer (a bootloader, a slow boot)
RECOVER_TIMEOUT_S = 20.0  # $X waits this long for a restarted board to be configured
DONE_MARGIN_S = 0.005
TRAIL_EXTRA_S = 1.0  # the pieces are kept this long beyond the lead (where the tool was)
STOP_FLUSH_S = 0.1  # a fault's emergency stop gets this long to leave before the link closes
STOP_READ_S = 0.5  # reading where a shut-down board stopped (a few round trips) takes at most
SLICE_END_S = 1e-6  # a sample this little past the last piece's end is a late tick's slice
SAMPLE_MARGIN_S = 0.005  # a sample asked for at the last moment comes this much before it
# (a woken loop is late by a millisecond or so, and the sample works a few before it sends)
SAMPLE_GAP_MAX_S = 0.17
"""The longest the samples may pause while steps or outputs are under way; within it, at
most the hold-back plus a flush (less ``SAMPLE_MARGIN_S``): what a sample does not yet
generate still leaves the ride-through the flushes kept (``lead_s`` - ``hold_back_s`` -
``flush_s``: 130 ms at the default lead), a run held back to grow leaves as late as the
flushes let it (runs as long: the same bytes), and a board's shutdown or fault mid-motion is
read (and alarmed) within it (165 ms at the default lead)."""


def level(value: float, top: int) -> int:
    """What the MCU is sent for ``value``: the PWM level out of ``top``, or on/off (top 0)."""
    if not top:
        return int(value > 0.5)
    return round(min(1.0, max(0.0, value)) * top)


def _lengthens(piece: Piece, before: Piece) -> bool:
    """Whether ``piece`` is ``before`` told again, longer (blocks that continue a run lengthen
    it: :meth:`~server.motion.pieces.PieceReporter.flush`): the same motion from the same
    start, so nothing that happens where a piece starts (the followed output turned on or off,
    the motors enabled, a rebase) happens again."""
    return (piece.start_s == before.start_s and piece.duration_s >= before.duration_s
            and piece.start_mm == before.start_mm and piece.unit == before.unit
            and piece.start_mm_s == before.start_mm_s
            and piece.accel_mm_s2 == before.accel_mm_s2 and piece.power == before.power)

class KlipperBackend:
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
        self.axes = [Axis(n, a.steps_per_mm, exact=[] if record else None)
                     for n, a in zip(core.axis_names, core.axes.values(), strict=True)]
        self.outputs = {name: Output(name, out) for name, out in cfg.outputs.items()}
        self.values: dict[str, float] = {}
        self.motors_on, self._enable_clock = True, 0
        self._motors_off_s = 0.0  # the motion time the drivers were last turned off at
        self.pwm_log: list[tuple[float, str, float, int]] | None = [] if record else None
        self.errors: list[FloatArray] | None = [] if record else None
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

    @property
    def tick_s(self) -> float:
        """The step generator ticks at most once a flush (less often while motion runs: see
        :meth:`next_sample_s`): steps, outputs and the followed output's power are timed from
        the pieces, not from the ticks."""
        return self.flush_s

    def follow_power(self, name: str, period_s: float) -> bool:
        """The output ``name`` follows each piece's ``power`` (updated at most every
        ``period_s`` along an acceleration): the laser's PWM from the same piece as its steps."""
        out = self.outputs.get(name)
        if out is None:
            return False
        self._follow, self._follow_period_s = out, period_s
        return True

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

    async def recover(self) -> None:
        """``$X``/M999: a shut-down board is restarted and configured afresh (waited for);
        CommandError while the board is not there or does not come back."""
        if self.ready and not self.shut_down:
            return
        if not self.shut_down:
            raise CommandError(Error.LOCKED_OUT, self.fault or
                               f"the MCU on {self.cfg.serial} is not connected yet")
        self._recover.set()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._configured.wait(), RECOVER_TIMEOUT_S)
        if not self.ready:
            raise CommandError(Error.LOCKED_OUT, "the MCU did not come back after its restart"
                               + (f": {self.fault}" if self.fault else ""))

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

    def trajectory(self, piece: Piece) -> None:
        if piece.duration_s > 0.0 and not self.ready:
            raise KlipperFault(self.fault or f"the MCU on {self.cfg.serial} is not ready")
        if piece.duration_s > 0.0:
            self._motion_end_s = piece.start_s + piece.duration_s
        else:
            self._motion_end_s = min(self._motion_end_s, piece.start_s)
        pieces = self._pieces
        while pieces and pieces[-1].start_s >= piece.start_s:
            pieces.pop()
        if pieces and pieces[-1].start_s + pieces[-1].duration_s > piece.start_s:
            last = pieces.pop()
            cut = replace(last, duration_s=piece.start_s - last.start_s)
            pieces.append(cut)
            if last is self._head:
                self._head = cut
        self._trail.cut(piece.start_s)
        if piece.duration_s > 0.0:
            pieces.append(piece)

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
            first = axis.first_clock()  # what it holds waits for its turn, as in _flush
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

    def set_output(self, name: str, value: float, time_s: float) -> None:
        self.values[name] = value
        out = self.outputs.get(name)
        if out is None or self.mcu is None or not self.ready:
            return
        if out is self._follow:
            self._follow_on = False  # set from outside: motion's end does not turn it off
        if value == out.value:
            return
        self._queue_output(out, value, self._when_s(time_s))
        self._pump()  # what is not due soon waits to share a block
        self._wake()  # refreshed from sample() while on

    def _refresh_outputs(self, time_s: float) -> None:
        """An output that is on is queued again (same value) every half ``max_duration``:
        the firmware turns it off by itself when these stop (motiond died or hung)."""
        for out in self.outputs.values():
            if out.value > 0.0 and out.max_ticks and (
                    self._scheduled_clock(time_s) - out.last_clock >= out.max_ticks // 2):
                self._queue_output(out, out.value, time_s)

    def _queue_output(self, out: Output, value: float, when_s: float) -> None:
        assert self.mcu is not None
        clock = max(self._scheduled_clock(when_s), out.last_clock + 1)
        out.last_clock, out.value = clock, value
        if self.pwm_log is not None:
            self.pwm_log.append((when_s, out.name, value, clock))
        d = self.mcu.dictionary
        if out.config.pwm:
            top = d.pwm_max
            level = round(min(1.0, max(0.0, value)) * top)
            message = d.encoder("queue_pwm_out")(out.oid, clock & 0xFFFFFFFF,
                                                 top - level if out.invert else level)
            self._queue.add(message, clock, clock)
        else:
            self._digital_out(out.oid, value > 0.5, out.invert, clock)

    def motors(self, enabled: bool, time_s: float) -> None:
        """M17 / M18, M84, ``$SLP``: the enable pins switch when motion reaches ``time_s``
        (off lets the axes be moved by hand; the next move turns them on again first)."""
        if self.mcu is None or not self.ready or enabled == self.motors_on:
            return
        when_s = self._when_s(time_s)
        if self._pieces:  # the motion it waited for has steps still to come: after them
            last = self._pieces[-1]
            when_s = max(when_s, last.start_s + last.duration_s)
        if not enabled:  # those pieces do not turn them on again: the next move's do
            self._motors_off_s = when_s
        self._switch_motors(enabled, self._scheduled_clock(when_s))
        self._pump()
        self._wake()  # ticks send it once due (it may wait to share a block)

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

    def _switch_motors(self, enabled: bool, clock: int) -> None:
        clock = self._enable_clock = max(clock, self._enable_clock + 1)  # in order, per pin
        self.motors_on = enabled
        for axis in self.axes:
            if axis.enable_oid is not None:
                self._digital_out(axis.enable_oid, enabled, axis.enable_inverted, clock)

    def _digital_out(self, oid: int, on: bool, inverted: bool, clock: int) -> None:
        assert self.mcu is not None
        message = self.mcu.dictionary.encoder("queue_digital_out")(
            oid, clock & 0xFFFFFFFF, int(on != inverted))
        self._queue.add(message, clock, clock)

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

    def halt(self) -> None:
        busy = self._busy()
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0
        if busy and self.mcu is not None and self.ready:
            log.warning("emergency stop sent to the MCU")
            self._mark_shut_down()  # nothing more goes out: the board is stopping
            self.mcu.emergency_stop()

    def _mark_shut_down(self) -> None:
        """The board is (about to be) shut down: nothing is sent until recover() restarts it."""
        self.ready, self.shut_down = False, True
        self._configured.clear()

    def close(self) -> None:
        if self.mcu is not None:
            if self.ready and self._busy():
                self.mcu.emergency_stop()
            self.mcu.close()
            self.mcu = None
        self.ready = False

    # -- the owned task -----------------------------------------------------------------------
    async def run(self) -> None:
        """Connect, configure and watch the MCU; on a fault stop the board, report it and
        reconnect; a shut-down board waits for :meth:`recover`, then is restarted."""
        restarted = False
        while True:
            mcu = Mcu(str(self.cfg.serial), self.cfg.baud, self.cfg.response_timeout_s)
            mcu.on_configured = self._on_configured
            self.mcu = mcu
            delay = self.retry_s
            try:
                await mcu.connect(self._config_commands, self.identity,
                                  RESTART_PATIENCE_S if restarted else CONNECT_TIMEOUT_S)
                self.identity = mcu.identity
                self.ready, self.fault, self.shut_down, restarted = True, None, False, False
                self._recover.clear()  # a $X that came while it was away is answered now
                self._configured.set()
                log.info("MCU on %s ready (%s, %s)", self.cfg.serial,
                         mcu.dictionary.constants.get("MCU"), mcu.dictionary.version)
                await mcu.watch()
            except NeedsRestart as exc:
                self.ready = False
                if restarted:
                    self._on_fault(f"{exc}, even after a restart")
                else:
                    log.warning("MCU on %s: %s: restarting it", self.cfg.serial, exc)
                    await mcu.restart(self.cfg.restart_method)
                    restarted, delay = True, RESTART_WAIT_S
            except McuShutdown as exc:
                await self._after_shutdown(mcu, exc)
                restarted, delay = True, RESTART_WAIT_S
            except (KlipperFault, ProtocolError, ConnectionError) as exc:
                if self.ready or self.shut_down:  # ours: outputs off first, if it still hears
                    mcu.emergency_stop()
                self.ready = False
                self._on_fault(str(exc))
                await self._drain(mcu, STOP_FLUSH_S)
            except asyncio.CancelledError:
                await self._stop_before_exit(mcu)
                raise
            finally:
                self.ready = False
                mcu.close()
            await asyncio.sleep(delay)

    async def _after_shutdown(self, mcu: Mcu, shutdown: McuShutdown) -> None:
        """The board shut down (our emergency stop or its own fault): read where it stopped,
        make that the machine position, alarm, and wait for :meth:`recover` to restart it."""
        self._mark_shut_down()
        cause = "emergency stop" if shutdown.requested else str(shutdown)
        self.fault = f"klipper MCU on {self.cfg.serial}: {cause}"  # what a new move is told
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0
        try:  # a board that stopped answering as it shut down: the alarm does not wait
            positions = await asyncio.wait_for(
                mcu.stopped_positions([axis.oid for axis in self.axes]), STOP_READ_S)
        except TimeoutError:
            positions = None
        if positions is None:
            where = "where it stopped is unknown"
        else:
            for axis, base, steps in zip(self.axes, self._config_base, positions, strict=True):
                axis.position = base + (-steps if axis.invert_dir else steps)
            stopped = [axis.position / axis.steps_per_mm for axis in self.axes]
            where = "stopped at " + " ".join(
                f"{axis.name.upper()}{mm:.3f}" for axis, mm in zip(self.axes, stopped,
                                                                    strict=True))
            self.relocate(stopped)
        self._on_fault(f"{cause}; {where} (position may be lost: re-home); $X or M999 "
                       "restarts the MCU")
        await self._recover.wait()
        self._recover.clear()
        await mcu.restart(self.cfg.restart_method)

    async def _drain(self, mcu: Mcu, limit_s: float) -> bool:
        """Wait (at most ``limit_s``) until what was queued for the MCU has left."""
        deadline = time.monotonic() + limit_s
        while (mcu.link.queued_bytes or mcu.link.window.inflight) and not mcu.link.closed:
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.01)
        return True

    async def _stop_before_exit(self, mcu: Mcu) -> None:
        """Shutting down with steps queued or a tool on: the emergency stop gets out first
        (bounded: at most ``EXIT_GRACE_S``)."""
        mcu.link.rest()  # no more ticks: acknowledgements are read as they arrive
        if not (self.ready and self._busy()):
            return
        mcu.emergency_stop()
        if not await self._drain(mcu, EXIT_GRACE_S):
            log.error("the MCU did not acknowledge the emergency stop before exit")

    def _on_fault(self, reason: str) -> None:
        message = f"klipper MCU on {self.cfg.serial}: {reason}"
        if message != self.fault:
            log.error("%s", message)
            pending = self._fault_to_raise  # the cause leads until the next tick raises it
            self._fault_to_raise = message if pending is None else f"{pending}; then {reason}"
            self._wake()  # raised from the next sample(), even on a resting machine
        self.fault = message
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0

    def _on_configured(self) -> None:
        self.motors_on, self._enable_clock = True, 0  # the configuration turns them on
        for axis in self.axes:
            axis.needs_reset, axis.sent_dir = True, 0
        self._config_base = [axis.position for axis in self.axes]
        for out in self.outputs.values():
            out.last_clock, out.value = 0, 0.0
        self._queue.in_use.clear()
        self._print.unanchor()

    def _config_commands(self, d: Dictionary) -> list[Command]:
        return config_commands(self.cfg, self.axes, self.outputs, d)

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
        if self._pieces or self._queue.waiting or any(a.segments or a.pending
                                                      for a in self.axes):
            return False
        now = self._now_clock()
        return all(a.compressor.last_clock < now for a in self.axes) and all(
            o.last_clock < now for o in self.outputs.values()) and self._enable_clock < now

    def _now_clock(self) -> float:
        return self._clock_at(time.monotonic())

    def _generate(self, until_s: float) -> None:
        """Exact step clocks of every axis (and the followed output's power) for the
        trajectory up to ``until_s``."""
        pieces = self._pieces
        spans = [Spans() for _ in self.axes]
        while pieces:
            piece = pieces[0]
            end_s = min(until_s, piece.start_s + piece.duration_s)
            rel_s = end_s - piece.start_s
            if rel_s < 0.0:
                break
            self._piece_steps(piece, rel_s, spans)
            if end_s < piece.start_s + piece.duration_s:
                break
            pieces.popleft()
            self._generated_s = end_s
        to_clock = (self._print.ref_clock, self._print.hz, self._print.ref_s)  # _motion_clock
        for axis, axis_spans in zip(self.axes, spans, strict=True):
            if not axis_spans.runs:
                continue
            clocks = axis_spans.solve(to_clock)
            first = 0
            for direction, count in axis_spans.runs:
                axis.add(direction, clocks[first:first + count])
                first += count
        out = self._follow
        if (self._follow_on and out is not None and not pieces
                and until_s > self._generated_s + SLICE_END_S):
            self._follow_on = False  # motion ended (not merely a slice of a late tick)
            self._set_followed(0.0, self._generated_s, self._level_top(out))

    def _follow_piece(self, piece: Piece, rel_s: float, first: bool) -> None:
        """The followed output's duty along ``piece`` up to ``rel_s`` into it. Turning on or
        off happens exactly where the piece starts; otherwise the duty is the piece's at
        every ``_follow_period_s`` of motion time (the laser's sample rate: S changing every
        segment of a fast raster costs at most one message a period)."""
        out, law, v0 = self._follow, piece.power, piece.start_mm_s
        assert out is not None
        start_s = piece.start_s
        top = self._level_top(out)
        if first:  # level(v, top) > 0 is v·top > 0.5 (a PWM level rounds to 0 up to 0.5)
            scale = top or 1
            on = out.value * scale > 0.5
            if law is None or not law.at(v0) * scale > 0.5:
                if on:
                    self._set_followed(0.0, start_s, top)
            elif not on:
                self._set_followed(law.at(v0), start_s, top)
                self._follow_next_s = start_s + self._follow_period_s
        if law is None:
            return
        t, a, end_s = max(self._follow_next_s, start_s), piece.accel_mm_s2, start_s + rel_s
        if t <= end_s:  # the grid: the output is looked at only where its duty may change
            period_s, set_followed = self._follow_period_s, self._set_followed
            if a == 0.0 or law.per_mm_s == 0.0:  # one duty along the piece: the first look
                set_followed(law.at(v0), t, top)  # decides (the others would see the same)
                while t <= end_s:
                    t += period_s  # the grid's times exactly as the looks would step them
            else:
                at = law.at
                while t <= end_s:
                    value = at(v0 + a * (t - start_s))
                    if value != out.value:
                        set_followed(value, t, top)
                    t += period_s
        self._follow_next_s = t

    def _set_followed(self, value: float, when_s: float, top: int) -> None:
        """The followed output set to ``value`` at ``when_s`` unless the MCU would be sent the
        level it has (``top``: :meth:`_level_top`)."""
        out = self._follow
        assert out is not None
        if value == out.value or level(value, top) == level(out.value, top):
            return
        self.values[out.name] = value
        self._follow_on = value > 0.0
        self._queue_output(out, value, when_s)

    def _level_top(self, out: Output) -> int:
        """An output's full-on level (the dictionary's ``PWM_MAX``), 0 if it is on/off only:
        what :func:`level` maps a value with."""
        if not out.config.pwm:
            return 0
        assert self.mcu is not None
        return self.mcu.dictionary.pwm_max

    def _piece_steps(self, piece: Piece, rel_s: float, spans: list[Spans]) -> None:
        """Each axis' whole steps along ``piece`` up to ``rel_s`` into it join ``spans``."""
        v0, a = piece.start_mm_s, piece.accel_mm_s2
        before = self._head
        first = piece is not before
        if first and before is not None and _lengthens(piece, before):
            self._head = piece  # the same motion carried on (a run of blocks: see pieces.py):
            self._trail.add(piece)  # steps and the followed output go on where they were
            first = False
        elif first:  # first look at this piece
            self._head = piece
            self._trail.add(piece)
            # the pieces of one block share its direction (the same tuple) and follow on from
            # each other: only the first of a block may start elsewhere
            if (before is None or piece.unit is not before.unit) and self._rebased(piece):
                return
            if (not self.motors_on and piece.duration_s > 0.0
                    and piece.start_s >= self._motors_off_s):  # enabled as it starts
                self._switch_motors(True, int(self._motion_clock(piece.start_s + self.lead_s)))
        if self._follow is not None:
            self._follow_piece(piece, rel_s, first)
        if rel_s == 0.0:
            return
        distance = v0 * rel_s + 0.5 * a * rel_s * rel_s
        base_s = piece.start_s + self.lead_s
        for axis, start, unit, axis_spans in zip(self.axes, piece.start_mm, piece.unit, spans,
                                                 strict=True):
            if unit == 0.0:
                continue
            per_mm = axis.steps_per_mm
            x0, u = start * per_mm, unit * per_mm
            target = floor(x0 + u * distance + 0.5)  # step_target, inline
            if target != axis.position:
                axis_spans.add(x0, u, v0, a, rel_s, axis.position, target, base_s)
                axis.position = target

    def _rebased(self, piece: Piece) -> bool:
        """A piece that starts away from where the steps are (the position was redefined,
        as homing does) moves the step count there without stepping."""
        jumped = False
        for axis, start in zip(self.axes, piece.start_mm, strict=True):
            here = start * axis.steps_per_mm
            if abs(here - axis.position) > 1.0:
                log.warning("axis %s redefined at %.3f mm: no steps sent", axis.name, start)
                axis.position = step_target(here)
                jumped = True
        return jumped and piece.duration_s == 0.0

    def _flush(self, now_s: float) -> None:
        """Compress what is due soon (all of it when motion has no more pieces): steps that
        may still join a longer run wait until their first is due within the lead less the
        hold-back (compressed once then, not at every flush). Of those, the runs complete
        before the last step known go; the last run waits on while its own first step is not
        yet due, so that it grows (a cruise is not cut where an acceleration's steps were
        sent). Motion has ended once the samples pass the last piece's end (a late tick's
        slice ends exactly on one)."""
        idle = not self._pieces and now_s > self._generated_s + SLICE_END_S
        force_clock = float(self._motion_clock(now_s + self.lead_s - self.hold_back_s))
        for axis in self.axes:
            if not idle and axis.holds(force_clock):
                continue  # nothing due: its run may still grow
            axis.collect()
            while axis.segments:
                direction, points = axis.segments[0]
                final = idle or len(axis.segments) > 1  # a direction change ends the run
                if not (final or points[0] < force_clock):
                    break
                done = self._emit(axis, direction, points, final)
                if done < len(points) and points[done] < force_clock:  # the last run is due
                    done += self._emit(axis, direction, points[done:], True)
                if done < len(points):
                    axis.segments[0] = (direction, points[done:])
                    break
                axis.segments.pop(0)

    def _emit(self, axis: Axis, direction: int, points: FloatArray, final: bool) -> int:
        assert self.mcu is not None
        d = self.mcu.dictionary
        compressor = axis.compressor
        oid, add_message = axis.oid, self._queue.add
        if axis.needs_reset or points[0] - compressor.last_clock > 2**30:
            start = int(points[0] - compressor.max_error) - 1
            compressor.last_clock, compressor.last_exact = start, float(start)
            add_message(d.encoder("reset_step_clock")(oid, start & 0xFFFFFFFF), None, start)
            axis.needs_reset = False
        if direction != axis.sent_dir:  # due with the first step it turns
            add_message(d.encoder("set_next_step_dir")(
                oid, int((direction > 0) != axis.invert_dir)), None, int(points[0]))
            axis.sent_dir = direction
        last = compressor.last_clock
        runs, done = compressor.compress_runs(points, final, self.errors)  # errors: how early
        if runs:  # encoded at once, each due (and its slot taken until) its first step
            self._queue.extend(d.step_encoder()(oid, runs, last)[0])
        return done

    def _pump(self) -> None:
        """Send queued messages in order while the MCU's move queue has room. Less than a
        block of messages all due later than a flush must send (``lead_s`` - ``hold_back_s``
        ahead) waits for more, at flushes and between them alike, so they share blocks; a
        message so held still leaves at least ``lead_s`` - ``hold_back_s`` - ``flush_s``
        ahead, as a held-back run does."""
        mcu = self.mcu
        if mcu is None or not self._queue.waiting:
            return
        now = self._now_clock()
        hold_after = None
        if mcu.clock is not None:
            hold_after = now + (self.lead_s - self.hold_back_s) * mcu.clock.freq_hz
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
        """The last step executes a lead time after the trajectory ends (+ the clock fit's
        possible lag behind the MCU's own clock)."""
        if not self.ready or not self._motion_end_s:
            return 0.0
        end_s = self._motion_end_s + self.lead_s
        if self.mcu is not None and self.mcu.clock is not None and self._print.anchored:
            end_s = self.mcu.clock.host_at(float(self._print.clock(end_s)))
        return end_s + DONE_MARGIN_S

    def _print_time_at(self, host_s: float) -> float:
        """The print time the MCU executes at host time ``host_s`` (through the fit)."""
        if self.mcu is None or self.mcu.clock is None or not self._print.anchored:
            return host_s
        return self._print.time_at(self.mcu.clock.clock_at(host_s))

    def _drop_motion(self) -> None:
        self._motion_end_s = 0.0
        self._trail.clear()
        self._follow_on = False
        self._pieces.clear()
        self._queue.waiting.clear()
        for axis in self.axes:
            axis.segments.clear()
            axis.pending.clear()
