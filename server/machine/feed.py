"""The machine's G-code feed: interpreter -> planner, with flow control and sync requests.

:class:`GcodeFeed` is the part of :class:`~server.machine.machine.Machine` (a base class of it)
that takes a line in: it runs the interpreter, feeds moves and ordered actions to the planner
(waiting while it is full: that wait is the flow control that delays a sender's ``ok``) and
carries out the interpreter's sync requests (M112, M999, messages, probing, ``M114``, ``M400``
waiting for motion to end, ``M410`` quickstop, and what modules registered). Its state is the
machine's, created by ``Machine.__init__``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import TYPE_CHECKING

from server.errors import Alarm, CommandError, Error, SoftLimitError
from server.machine.parts import on_step_grid
from server.motion.feed import offer
from server.motion.moves import Action, ActionName, Move, MoveKind, Output, Sync, SyncKind
from server.runtime.events import MachineState

if TYPE_CHECKING:
    from server.config import CoreConfig
    from server.gcode.interpreter import Interpreter
    from server.gcode.plain import PlainSpan
    from server.machine.machine import SyncHandler
    from server.motion.planner import Planner
    from server.motion.stepgen import StepGenerator
    from server.runtime.clock import Clock
    from server.runtime.dispatcher import Command
    from server.runtime.state import MachineStatus


_RUN, _IDLE = MachineState.RUN, MachineState.IDLE  # (an enum member's look-up costs a call)
_WAIT = Sync(SyncKind.WAIT)
SPAN_READING_OUTPUTS = 50  # a span queues at most this many outputs a reading (a job's player
# then gives the loop a turn if it has had its own: a reading holds it well under a millisecond)


def _has_dwell(outputs: list[Output]) -> bool:
    """Whether a line's outputs hold a ``G4`` dwell (it stops motion: never in a move)."""
    return any(type(out) is Action and out.name == ActionName.DWELL for out in outputs)


class GcodeFeed:
    """Lines into the planner; see the module docstring."""

    # The machine's state this part reads and writes (set by Machine.__init__).
    core: CoreConfig
    clock: Clock
    status: MachineStatus
    interpreter: Interpreter
    planner: Planner
    stepgen: StepGenerator
    room: asyncio.Event
    idle_event: asyncio.Event
    check_mode: bool
    epoch: int
    sync_handlers: dict[SyncKind, SyncHandler]

    if TYPE_CHECKING:
        def emergency_stop(self) -> None: ...  # the machine's realtime commands
        async def unlock(self) -> None: ...  # the machine's
        def quickstop(self, reason: str = ...) -> None: ...

    # -- the G-code handler -----------------------------------------------------------------
    def handle_gcode(self, command: Command) -> list[str] | Awaitable[list[str]]:
        """The line's messages once its outputs are all in the planner: at once when the
        planner has room and the line asks for no sync, else an awaitable of them (see
        :meth:`~server.runtime.dispatcher.Dispatcher.begin`)."""
        outputs = self.interpret(command)
        if len(outputs) != 1 or type(outputs[0]) is not Move:  # (a probe is a Sync)
            self._arm_probe(outputs)
            if _has_dwell(outputs) and getattr(command.source, "dwell_waits", False):
                outputs.append(_WAIT)  # Grbl's G4: ok once the motion and the dwell have run
        return self._queue(outputs)

    def handle_span(self, span: PlainSpan) -> list[str] | Awaitable[list[str]]:
        """A span of a job's plain lines (:func:`~server.gcode.plain.plain_items`) read at
        once as far as the interpreter takes them, queued as far as the planner has room
        (``span.taken``: the lines whose outputs are all in the planner; the interpreter is
        left after them, where the next reading of the span goes on): the same outputs, in
        the same order, as each line through :meth:`handle_gcode`. Waits for room first when
        the planner is full, as a line does before its first output; queues one line's
        outputs alone when ``span.hurry()`` says a line waits for the next line boundary (a
        job's baby-step)."""
        if self.check_mode or not self.planner.is_full():
            return self._read_span(span)
        return self._span_after_room(span, self.epoch)

    async def _span_after_room(self, span: PlainSpan, epoch: int) -> list[str]:
        await self._wait_for_room(epoch)
        return self._read_span(span)

    def _read_span(self, span: PlainSpan) -> list[str]:
        interpreter = self.interpreter
        if span.run is None or span.state != interpreter.runs_state():  # (read afresh when
            span.read(interpreter.execute_plain(  # a line ran since: a baby-step)
                span.columns, span.start + span.taken, span.stop))
        run, outputs, start = span.run, span.outputs, span.queued
        assert run is not None
        one = span.hurry is not None and span.hurry() and start < len(outputs)
        stop = start + 1 if one else min(len(outputs), start + SPAN_READING_OUTPUTS)
        index = span.queued = self._offer(outputs, start, stop)
        lines = run.count if index == len(outputs) else span.lines[index]
        interpreter.rewind(run, lines)  # (where the run's lines in the planner leave it)
        span.taken = span.first + lines
        span.state = interpreter.runs_state()
        return []

    def _queue(self, outputs: list[Output]) -> list[str] | Awaitable[list[str]]:
        """Offer a line's outputs; nothing when all were taken, else the wait for the rest."""
        epoch = self.epoch
        index = self._offer(outputs, 0)
        if index == len(outputs):
            return []
        return self._feed(outputs, index, epoch)

    def interpret(self, command: Command) -> list[Output]:
        """The line's outputs from the interpreter; a target outside the travel alarms,
        unless the line's source says otherwise (``soft_limit_alarms``: a RepRap host)."""
        assert command.line is not None
        try:
            return self.interpreter.execute(command.line)
        except SoftLimitError as exc:
            if getattr(command.source, "soft_limit_alarms", True):
                self.status.alarm(Alarm.SOFT_LIMIT, f"soft limit: {exc.message}")
            raise

    async def _feed(self, outputs: list[Output], index: int, epoch: int) -> list[str]:
        """The rest of a line's outputs from ``index`` on (:meth:`_offer`), waiting for room
        and carrying out sync requests in order (``epoch``: the machine's when the line
        began)."""
        messages: list[str] = []
        while index < len(outputs):
            output = outputs[index]
            if type(output) is Sync:
                messages += await self.sync(output)
                index += 1
            else:
                await self._wait_for_room(epoch)
            index = self._offer(outputs, index)
        return messages

    def _offer(self, outputs: list[Output], index: int, stop: int | None = None) -> int:
        """Offer ``outputs[index:stop]`` to the planner (:func:`~server.motion.feed.offer`,
        as ``estimate`` does) up to the next sync request or a full planner; in check mode
        they are interpreted, never planned. Returns the index of the first output not
        taken."""
        stop = len(outputs) if stop is None else stop
        if self.check_mode:
            while index < stop and type(outputs[index]) is not Sync:
                index += 1
            return index
        taken = offer(self.planner, outputs, index, stop)
        if taken > index:
            self._note_input(_RUN)
        return taken

    def _arm_probe(self, outputs: list[Output]) -> None:
        for output in outputs:
            if type(output) is Sync and output.kind is SyncKind.PROBE:
                self.stepgen.probe_towards = bool(output.params.get("towards", True))
                self.stepgen.probe_hit = False

    async def queue_move(self, move: Move) -> None:
        """Append a move, waiting while the planner is full."""
        if self.check_mode:
            return
        await self._wait_for_room()
        self.planner.append(move)
        self._note_input(MachineState.JOG if move.kind is MoveKind.JOG else MachineState.RUN)

    async def queue_action(self, action: Action) -> None:
        """Append an ordered action, waiting while the planner is full."""
        if self.check_mode:
            return
        await self._wait_for_room()
        self.planner.append_action(action)
        self._note_input(MachineState.RUN)

    async def _wait_for_room(self, epoch: int | None = None) -> None:
        """Wait while the planner is full; refuse the line if motion was reset meanwhile
        (``epoch``: the machine's epoch when the line began; default now)."""
        epoch = self.epoch if epoch is None else epoch
        while self.planner.is_full():
            self.room.clear()
            await self.room.wait()
        if epoch != self.epoch:
            raise CommandError(
                Error.BUSY, "motion was reset while this line waited; it was not run"
            )

    def _note_input(self, state: MachineState) -> None:
        self.idle_event.clear()
        self.stepgen.note_input(self.clock.now_s())
        if self.status.state is _IDLE:
            self.status.set_state(state)

    async def wait_idle(self) -> None:
        """Wait until every queued move has been executed, by the hardware too: a Klipper
        MCU runs a lead time behind the step generator, whose end sets the idle event only
        once the board's last step has run (:meth:`Machine.on_idle`)."""
        if not self.stepgen.idle:
            self.idle_event.clear()
            self.stepgen.request_start()
        await self.idle_event.wait()

    # -- sync requests ----------------------------------------------------------------------
    async def sync(self, request: Sync) -> list[str]:
        """Carry out an interpreter request that needs the machine."""
        kind = request.kind
        if kind is SyncKind.HALT:
            self.emergency_stop()
            return []
        if kind is SyncKind.CLEAR_HALT:
            await self.unlock()
            return []
        if kind is SyncKind.MESSAGE:
            return list(request.params["lines"])
        if kind is SyncKind.QUICKSTOP:
            self.quickstop()
            return []
        handler = self.sync_handlers.get(kind)
        if handler is not None:
            return await handler(request.params)
        if kind is SyncKind.HOME:  # no module carries it out
            raise CommandError(
                Error.SETTING_DISABLED, "homing is not configured: add an [endstops] section"
            )
        await self.wait_idle()
        if kind is SyncKind.WAIT:
            return []
        if kind is SyncKind.REPORT_POSITION:
            return [self.position_report()]
        return self._finish_probe(request)

    def _finish_probe(self, request: Sync) -> list[str]:
        position = self.stepgen.state.position_mm
        success = self.stepgen.probe_hit
        self.interpreter.set_position(position)
        self.planner.set_position(position)
        self.interpreter.record_probe(position, success)
        coords = ",".join(f"{v:.3f}" for v in on_step_grid(position, self.core))
        report = f"[PRB:{coords}:{int(success)}]"
        if not success and request.params.get("error_on_fail", True):
            self.status.alarm(5, "probe fail: the probe did not change state within the move")
        return [report]

    def position_report(self) -> str:
        """Smoothie's M114 answer: work position, then machine position. The work position
        has Marlin's ``E:`` (no extruder: 0) after Z, where RepRap hosts (OctoPrint's pause
        position) look for ``X: Y: Z: E:``."""
        machine = self.stepgen.state.position_mm
        work = self.interpreter.work_position(machine)
        names = self.core.axis_names
        words = [f"{n}:{v:.4f}" for n, v in zip(names, work, strict=True)]
        words.insert(names.index("Z") + 1 if "Z" in names else len(words), "E:0.0000")
        mpos = " ".join(f"{n}:{v:.4f}" for n, v in zip(names, machine, strict=True))
        return f"C: {' '.join(words)} MPos: {mpos}"
