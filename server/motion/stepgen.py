"""The step generator: advances planned blocks on a fixed-rate clock and emits whole steps.

The core (:meth:`StepGenerator.tick`) is pure: given a time, it walks the analytic trapezoids
of the blocks from the planner, computes where every axis must be, and emits the whole steps
that take each axis there. A late tick only makes the next call cover more time: the path, the
planned timing and the step count never depend on jitter, and at the end of every block the
position is the block's exact end, so emitted steps always sum to the commanded position.

Feed hold decelerates along the path (across block boundaries when needed) within the
acceleration limit; resume re-plans the rest of the interrupted block from standstill.
:mod:`server.runtime.ticks` is the thin asyncio task that calls :meth:`advance` at ``tick_hz``
(or when :meth:`next_tick_s` says: a backend that times its own steps is sampled when it needs).
One call goes through at most ``max_blocks_per_call`` blocks (64, or the backend's
``blocks_per_call``): a tick late by many blocks (at 20,000 segments/s a 50 ms stall is 1,000
blocks) is caught up in slices, with the event loop running other callbacks in between,
instead of in one long call. A backend that times its own steps (a Klipper MCU) also gets
the trajectory as pieces (:mod:`server.motion.pieces`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from server.motion.backend import Backend
from server.motion.motion_state import HoldState, MotionListener, MotionState
from server.motion.moves import Action, MoveKind, Position
from server.motion.pieces import PieceReporter, PowerOf
from server.motion.planner import Block, Planner
from server.motion.planner_intake import Geometry

LENGTHEN_CHUNK = 32
"""Blocks whose numbers :meth:`StepGenerator._lengthen` reads at once (most ticks end within
a few dozen: numbers read for blocks past the tick's end are read again at the next)."""


@dataclass(slots=True)
class _Cursor:
    """Where the generator is: the current block and the time (or distance, in hold) into it."""

    block: Block | None = None
    time_s: float = 0.0
    distance_mm: float = 0.0
    hold_speed_mm_s: float = 0.0
    hold_accel_mm_s2: float = 0.0
    steps: list[int] = field(default_factory=list)


class StepGenerator:
    """Turns planned blocks into steps at fixed-rate ticks; see the module docstring."""

    def __init__(
        self,
        planner: Planner,
        backend: Backend,
        steps_per_mm: tuple[float, ...],
        listener: MotionListener,
        *,
        tick_hz: float = 1000.0,
        start_delay_s: float = 0.05,
        max_blocks_per_call: int | None = None,
    ) -> None:
        self.planner = planner
        self.backend = backend
        self.steps_per_mm = steps_per_mm
        self.listener = listener
        # a backend that times its own steps from the pieces needs fewer ticks (Klipper's)
        self.tick_s = getattr(backend, "tick_s", None) or 1.0 / tick_hz
        self.start_delay_s = start_delay_s
        self.max_blocks_per_call = max_blocks_per_call or int(
            getattr(backend, "blocks_per_call", 64))
        self.last_input_s = -math.inf
        self.before_pop: Callable[[], None] | None = None  # offline feeders refill here
        self.probe_towards = True  # G38.2/3 stop on contact; G38.4/5 on loss of contact
        self.probe_hit = False
        self.flush_requested = False
        self.state = MotionState(position_mm=planner.position_mm)
        self._cursor = _Cursor(
            steps=[round(p * s) for p, s in zip(planner.position_mm, steps_per_mm, strict=True)]
        )
        self._running = False
        self._last_tick_s: float | None = None
        # backends that time their own steps get the trajectory as pieces
        self._pieces = PieceReporter(backend) if backend.wants_trajectory else None
        self._resume_when_stopped = False
        # the start of the block whose ordered actions run now (outputs they set are timed there)
        self.action_s: float | None = None
        # Called when motion may start (input, a start request): the task sleeps while idle.
        self.wake: Callable[[], None] = lambda: None
        # Set by the ticking task: the next tick comes within the given seconds (the tick
        # schedule did not foresee this: a hold, a halt, input while nothing runs).
        self.hurry: Callable[[float], None] = lambda within_s: None
        # The backend's next need of a sample, if it says (see next_tick_s)
        self._next_sample_s: Callable[[float], float] | None = getattr(
            backend, "next_sample_s", None)

    # -- control (called by the machine) ----------------------------------------------------
    @property
    def idle(self) -> bool:
        """Nothing executing, nothing queued."""
        return self._cursor.block is None and len(self.planner) == 0

    @property
    def can_sleep(self) -> bool:
        """Nothing to tick for until :attr:`wake` is called: idle, not held, and a backend
        that needs no ticks while nothing moves."""
        return (self.idle and self.state.hold is HoldState.NONE
                and not getattr(self.backend, "ticks_when_idle", True))

    def note_input(self, now_s: float) -> None:
        """A block was appended at ``now_s``: motion starts after a short settling delay."""
        self.last_input_s = now_s
        self.wake()
        if self._cursor.block is None:  # nothing under way: ticks at tick_s until it starts
            self.hurry(self.tick_s)

    def request_start(self) -> None:
        """Start executing queued blocks at the next tick, without waiting for more input."""
        self.flush_requested = True
        self.wake()
        self.hurry(0.0)

    def hold(self) -> None:
        """Feed hold: decelerate to a stop along the path."""
        cursor = self._cursor
        if self.state.hold is not HoldState.NONE:
            return
        if cursor.block is None:  # nothing running: held at once (Grbl's Hold:0 when idle)
            self._set_hold(HoldState.STOPPED)
            return
        cursor.distance_mm = cursor.block.distance_at(cursor.time_s)
        cursor.hold_speed_mm_s = cursor.block.speed_at(cursor.time_s)
        cursor.hold_accel_mm_s2 = cursor.block.accel_mm_s2 or math.inf
        self._set_hold(HoldState.DECELERATING)
        self.hurry(0.0)  # the deceleration's steps at once, not at a sparse tick

    def resume(self) -> None:
        """Cycle start: continue from exactly where the hold stopped."""
        if self.state.hold is HoldState.DECELERATING:
            self._resume_when_stopped = True
            return
        if self.state.hold is not HoldState.STOPPED:
            return
        cursor = self._cursor
        block = cursor.block
        if block is not None and cursor.distance_mm < block.length_mm - 1e-12:
            rest = self.planner.make_block(self.state.position_mm, block.end_mm, block.move, [])
            self.planner.insert_front(rest)
        cursor.block = None
        cursor.time_s = cursor.distance_mm = 0.0
        self.planner.set_start_speed(0.0)
        self._running = True
        self._set_hold(HoldState.NONE)
        self.hurry(0.0)

    def stop_now(self) -> list[Action]:
        """Halt: stop at once where the steps are, drop everything queued."""
        cursor = self._cursor
        cursor.block = None
        cursor.time_s = cursor.distance_mm = 0.0
        self._running = False
        self._resume_when_stopped = False
        self.flush_requested = False
        dropped = self.planner.flush()
        self.planner.set_position(self.state.position_mm)
        self.planner.set_start_speed(0.0)
        self._set_hold(HoldState.NONE)
        self._publish_still()
        if self._last_tick_s is not None and self._pieces is not None:  # the rest is dropped
            self._pieces.stop(self._last_tick_s, self.state.position_mm)
        self.hurry(0.0)  # the ticks see the stop (and may rest) at once
        return dropped

    # -- the tick ---------------------------------------------------------------------------
    def tick(self, now_s: float) -> None:
        """Advance motion to ``now_s`` and emit the steps that take every axis there."""
        while not self.advance(now_s):
            pass

    def advance(self, now_s: float) -> bool:
        """Advance motion towards ``now_s`` through at most ``max_blocks_per_call`` blocks and
        emit the steps for the time reached; True once that is ``now_s``. The time reached is
        always on the planned timeline: slicing changes neither the path nor the steps."""
        last = self._last_tick_s
        if last is None or now_s <= last:
            self._last_tick_s = now_s
            return True
        dt = now_s - last
        hold = self.state.hold
        behind_s = 0.0
        if hold is HoldState.NONE:
            behind_s = self._advance(dt, now_s)
        elif hold is HoldState.DECELERATING:
            self._decelerate(dt)
        reached_s = now_s - behind_s if behind_s else now_s
        self._last_tick_s = reached_s
        self._emit(reached_s)
        return not behind_s

    def _advance(self, dt: float, now_s: float) -> float:
        """Move the cursor ``dt`` on; the seconds left over when the block budget ran out (the
        cursor then waits at the end of the last block, still moving)."""
        cursor = self._cursor
        t = cursor.time_s + dt
        block = cursor.block
        budget = self.max_blocks_per_call
        pieces = self._pieces
        while True:
            if block is None:
                if pieces is not None and pieces.lengthening and self._running and budget > 1:
                    t, budget = self._lengthen(now_s, t, budget)
                block = self._next_block(now_s, now_s - t)
                budget -= 1
                if block is None:
                    t = 0.0
                    break
                if self.state.hold is not HoldState.NONE:  # a pause action stopped us
                    cursor.block, cursor.time_s, cursor.distance_mm = block, 0.0, 0.0
                    return 0.0
                if pieces is not None:
                    pieces.block(now_s - t, block)
            if t < block.duration_s:
                break
            if budget <= 0:
                behind_s = t - block.duration_s
                cursor.block, cursor.time_s = block, block.duration_s
                self.state.motion_time_s += dt - behind_s
                return behind_s
            t -= block.duration_s
            state = self.state  # (_finish, without a call: once a block)
            state.position_mm = block.end_mm
            state.blocks_done += 1
            block = None
        cursor.block, cursor.time_s = block, t
        if block is not None:
            self.state.motion_time_s += dt
        return 0.0

    def _lengthen(self, now_s: float, left_s: float, budget: int) -> tuple[float, int]:
        """The blocks from the planner's head that only lengthen the open piece and end
        within this call, taken at once (:meth:`PieceReporter.lengthen`, a chunk of their
        numbers at a time): what as many turns of :meth:`_advance`'s loop would do with
        them, without a block object each. Returns the time left and the budget left (at
        least one block, for the next)."""
        pieces, planner = self._pieces, self.planner
        assert pieces is not None
        if self.before_pop is not None:
            return left_s, budget
        final = min(planner.final_count(), budget - 1)
        taken: list[list[float]] = []
        end: Geometry | None = None
        while len(taken) < final:
            rows, geometry = planner.final_rows(len(taken), min(final - len(taken),
                                                                LENGTHEN_CHUNK))
            count, left_s = pieces.lengthen(now_s, left_s, rows, geometry)
            if count:
                taken += rows[:count]
                end = geometry[count - 1]
            if count < len(rows):
                break
        if end is not None:
            planner.drop_head(taken)
            move, _, _, end_mm, _ = end
            state = self.state
            state.kind = move.kind if move is not None else None
            state.position_mm = end_mm
            state.blocks_done += len(taken)
        return left_s, budget - len(taken)

    def _next_block(self, now_s: float, start_s: float) -> Block | None:
        planner = self.planner
        if not self._running:
            if len(planner) == 0:
                return None
            ready = (
                planner.is_full()
                or self.flush_requested
                or now_s - self.last_input_s >= self.start_delay_s
            )
            if not ready:
                return None
            self._running = True
        block = self.pop_block()
        pieces = self._pieces
        if block is None:
            self._running = False
            self.flush_requested = False
            if pieces is not None:
                pieces.flush()
            self.listener.on_idle()
            return None
        self.state.kind = block.move.kind if block.move else None
        if block.actions:
            if pieces is not None:  # an action may read the trajectory (M18 waits for it)
                pieces.flush()
            self.action_s = start_s
            try:
                for action in block.actions:
                    self.listener.on_action(action)
            finally:
                self.action_s = None
        return block

    def motion_time_s(self, now_s: float) -> float:
        """When an output set at ``now_s`` takes effect on the motion's timeline. For a
        backend that times its own steps from the pieces (ticks a flush apart): at the start
        of the block whose actions run (exact, whatever the tick), else at the last tick while
        moving (where a feed hold's deceleration starts). Otherwise, and when still: ``now_s``
        (the tick itself is the timeline)."""
        if self._pieces is None:
            return now_s
        if self.action_s is not None:
            return self.action_s
        if self._cursor.block is not None and self._last_tick_s is not None:
            return min(now_s, self._last_tick_s)
        return now_s

    def follow_power(self, power_of: PowerOf) -> None:
        """Give each piece its tool power (``power_of(move, nominal_mm_s)``): the backend
        times the output from the pieces (see :mod:`server.motion.pieces`)."""
        if self._pieces is not None:
            self._pieces.power_of = power_of

    def pop_block(self) -> Block | None:
        """The next block, re-planned first when the last plan's look-ahead ran short.

        Only the popped block's speeds are ever used, so planning at pop time is enough; doing
        it only when the last plan's window end could still shape the head (see
        :meth:`Planner.lookahead_short`) batches re-planning without changing any speed, and
        keeps it a function of the block sequence alone, identical for live execution and the
        offline estimate.
        """
        planner = self.planner
        if self.before_pop is not None:
            self.before_pop()
        if planner.lookahead_short():
            planner.plan()
        return planner.pop()

    def _finish(self, block: Block) -> None:
        self.state.position_mm = block.end_mm
        self.state.blocks_done += 1

    def _decelerate(self, dt: float) -> None:
        cursor = self._cursor
        v, a = cursor.hold_speed_mm_s, cursor.hold_accel_mm_s2
        used_s = min(dt, v / a) if a != math.inf else 0.0
        if self._pieces is not None:
            self._pieces.hold(cursor.block, cursor.distance_mm,
                              self._last_tick_s or 0.0, v, a, used_s)
        cursor.distance_mm += v * used_s - 0.5 * a * used_s * used_s if used_s else 0.0
        cursor.hold_speed_mm_s = max(0.0, v - a * used_s) if used_s else 0.0
        block = cursor.block
        while block is not None and cursor.distance_mm > block.length_mm:
            overflow = cursor.distance_mm - block.length_mm
            self._finish(block)
            block = self.pop_block()
            cursor.block, cursor.distance_mm = block, overflow
            if block is None:
                cursor.hold_speed_mm_s = 0.0
            else:
                for action in block.actions:
                    self.listener.on_action(action)
                block.actions = []
                if self._pieces is not None:
                    self._pieces.hold_into(block, self._last_tick_s or 0.0, overflow, v, a, used_s)
                cursor.hold_accel_mm_s2 = min(
                    cursor.hold_accel_mm_s2, block.accel_mm_s2 or math.inf
                )
        if cursor.hold_speed_mm_s <= 0.0:
            self._set_hold(HoldState.STOPPED)
            self.listener.on_hold_stopped()
            if self._resume_when_stopped:
                self._resume_when_stopped = False
                self.resume()

    # -- output -----------------------------------------------------------------------------
    def _emit(self, now_s: float) -> None:
        cursor = self._cursor
        state = self.state
        block = cursor.block
        if block is None:
            self._publish_still()
            position = state.position_mm
        else:
            if state.hold is HoldState.NONE:
                distance = block.distance_at(cursor.time_s)
                state.speed_mm_s = block.speed_at(cursor.time_s)
            else:
                distance = min(cursor.distance_mm, block.length_mm)
                state.speed_mm_s = cursor.hold_speed_mm_s
            position = tuple(
                start + unit * distance
                for start, unit in zip(block.start_mm, block.unit, strict=True)
            )
            state.position_mm = position
            state.moving = True
            move = block.move
            state.nominal_mm_s = block.nominal_mm_s
            if move is not None:
                state.tool_mode, state.s_value = move.tool_mode, move.s_value
                state.line_number = move.line_number
        state.time_s = now_s
        state.queue_depth = len(self.planner)
        if self._pieces is None:  # whole steps a tick (a backend that times its own steps
            self._step_to(now_s, position)  # from the pieces has no use for them)
        else:
            self._pieces.flush()
        self.backend.sample(now_s, position, state.speed_mm_s)
        if block is not None and state.kind is MoveKind.PROBE:
            self._check_probe(position)

    def _check_probe(self, position: Position) -> None:
        """A probing move stops where the probe input changes (G38.2/3 contact, G38.4/5 loss)."""
        if self.backend.probe_triggered(position) == self.probe_towards:
            self.probe_hit = True
            self.stop_now()
            self.listener.on_idle()

    def _publish_still(self) -> None:
        state = self.state
        state.speed_mm_s = 0.0
        state.moving = False

    def _step_to(self, now_s: float, position: Position) -> None:
        steps = self._cursor.steps
        deltas = []
        moved = False
        for axis, (mm, per_mm) in enumerate(zip(position, self.steps_per_mm, strict=True)):
            target = round(mm * per_mm)
            delta = target - steps[axis]
            if delta:
                steps[axis] = target
                moved = True
            deltas.append(delta)
        if moved:
            self.backend.step(now_s, deltas)

    def _set_hold(self, hold: HoldState) -> None:
        self.state.hold = hold

    def set_steps_per_mm(self, steps_per_mm: tuple[float, ...]) -> None:
        """Change the resolution (only while idle): step counts are re-based on the position."""
        self.steps_per_mm = steps_per_mm
        self.rebase(self.state.position_mm)

    def rebase(self, position_mm: Position) -> None:
        """Declare the tool to be at ``position_mm`` without moving (homing); idle only."""
        self.state.position_mm = position_mm
        self._cursor.steps = [
            round(p * s) for p, s in zip(position_mm, self.steps_per_mm, strict=True)
        ]

    @property
    def steps(self) -> tuple[int, ...]:
        """Whole steps emitted so far per axis (absolute; not kept for a backend that times
        its own steps from the pieces)."""
        return tuple(self._cursor.steps)

    # -- the task's hooks (server.runtime.ticks runs the ticks) -----------------------------
    def next_tick_s(self, due_s: float, now_s: float) -> float:
        """When the tick after the one due at ``due_s`` (run at ``now_s``) is due: a
        ``tick_s`` on, or later when the backend says when it next needs a sample
        (``next_sample_s``: a backend that times its own steps from the pieces) while motion
        needs nothing of the ticks themselves: no hold decelerating, no start pending, no
        probing or homing move (checked at each tick). Whatever changes that between ticks
        (:meth:`hold`, :meth:`resume`, :meth:`stop_now`, input, a start) calls :attr:`hurry`."""
        tick_s = due_s + self.tick_s
        next_sample_s = self._next_sample_s
        if next_sample_s is None or not self._sparse_ok():
            return tick_s
        return max(tick_s, next_sample_s(now_s))

    def _sparse_ok(self) -> bool:
        """Whether motion needs no tick of its own until the backend's next sample."""
        state, block = self.state, self._cursor.block
        if state.hold is HoldState.DECELERATING:
            return False
        if block is None:
            return len(self.planner) == 0  # else a start is pending
        return state.kind not in (MoveKind.PROBE, MoveKind.HOMING)

    def resume_at(self, time_s: float) -> None:
        """The timeline (re)starts at ``time_s``: no catching up on time not ticked (the
        task's start, a sleep while idle)."""
        self._last_tick_s = time_s
