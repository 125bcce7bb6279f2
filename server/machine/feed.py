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
from server.gcode.plain import MIN_RUN
from server.machine.parts import on_step_grid
from server.motion.feed import MoveRun, offer, offer_run
from server.motion.moves import Action, ActionName, Move, MoveKind, Output, Sync, SyncKind
from server.runtime.events import MachineState

if TYPE_CHECKING:
    import numpy as np

    from server.config import CoreConfig
    from server.gcode.interpreter import Interpreter
    from server.machine.machine import SyncHandler
    from server.motion.planner import Planner
    from server.motion.stepgen import StepGenerator
    from server.runtime.clock import Clock
    from server.runtime.dispatcher import Command
    from server.runtime.state import MachineStatus


RUN_DRAIN = 0.25  # a run waits for room until the window drained this share of it at most:
# lines longer than max_planned_s * RUN_DRAIN / MIN_RUN each go one by one
RUN_FILL = 128  # a run waits for room for this many lines (within RUN_DRAIN): one costs about
# 200 µs and 2.7 µs a line, a line alone 7 µs (the simulated machine, in process)
RUN_LINE_S_DECAY = 0.9  # while they do, the last run's time a line decays: a run is tried again
_RUN, _IDLE = MachineState.RUN, MachineState.IDLE  # (an enum member's look-up costs a call)
_WAIT = Sync(SyncKind.WAIT)


def _has_dwell(outputs: list[Output]) -> bool:
    """Whether a line's outputs hold a ``G4`` dwell (it stops motion: never in a move)."""
    return any(type(out) is Action and out.name == ActionName.DWELL for out in outputs)


class GcodeFeed:
    """Lines into the planner; see the module docstring."""

    feeds_runs = True  # a job's runs of plain lines are fed at once (feed_plain)
    line_s = 0.0  # the time the last run's lines took each (its estimate; 0: none yet)
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
        epoch = self.epoch
        index = self._offer(outputs, 0)
        if index == len(outputs):
            return []
        return self._feed(outputs, index, epoch)

    def feed_plain(self, columns: dict[str, np.ndarray], start: int, stop: int
                   ) -> int | Awaitable[int]:
        """Plain lines ``start`` to ``stop`` of a parsed chunk (a playing job's:
        :func:`~server.gcode.plain.plain_spans`), as many as the planner has room for, at
        once, as :meth:`handle_gcode` of each would (read with numpy:
        :meth:`~server.gcode.interpreter.Interpreter.read_plain`; appended with
        :func:`~server.motion.feed.offer_run`). Nothing is read ahead of the planner, so what
        comes after them in the stream (a line interjected) runs as soon as it would after the
        same lines one by one.

        A run costs about as much as ``MIN_RUN`` lines one by one: one is read only when the
        lines are short (the last run's took ``line_s`` each: ``MIN_RUN`` of them within
        ``RUN_DRAIN`` of the window, a raster's), and, when the planner has less room than
        ``MIN_RUN`` of them, once it has (an awaitable that waits, holding the lines' turn as
        a line waiting for room does). Returns how many lines it read, or an
        awaitable of that: 0 when the first line is the one-line path's (the state takes no
        runs, or the lines are long)."""
        if not self.interpreter.takes_runs():
            return 0
        if self.check_mode:
            run = self.interpreter.execute_plain(columns, start, stop)
            return run.count
        if self.line_s * MIN_RUN > self.planner.settings.max_planned_s * RUN_DRAIN:
            self.line_s *= RUN_LINE_S_DECAY  # (the lines may grow short again: try now and then)
            return 0
        if self.planner.room_s() >= self._run_room_s() and not self.planner.is_full():
            return self._read_run(columns, start, stop, self.epoch)
        return self._run_with_room(columns, start, stop, self.epoch)

    async def _run_with_room(self, columns: dict[str, np.ndarray], start: int, stop: int,
                             epoch: int) -> int:
        """:meth:`feed_plain` once the planner has room for ``MIN_RUN`` of the lines."""
        while self.planner.is_full() or self.planner.room_s() < self._run_room_s():
            self.room.clear()  # (set again after each tick while the window has room)
            await self.room.wait()
            if epoch != self.epoch:
                raise CommandError(Error.BUSY, "motion was reset while these lines waited; "
                                   "they were not run")
        read = self._read_run(columns, start, stop, epoch)
        return read if isinstance(read, int) else await read

    def _run_room_s(self) -> float:
        """The room a run waits for: ``RUN_FILL`` lines, within ``RUN_DRAIN`` of the window."""
        return min(RUN_FILL * self.line_s, self.planner.settings.max_planned_s * RUN_DRAIN)

    def _read_run(self, columns: dict[str, np.ndarray], start: int, stop: int,
                  epoch: int) -> int | Awaitable[int]:
        """Read the lines the planner has room for now (the last run's time a line, and a
        quarter more, then exactly: :meth:`~server.motion.planner.Planner.room_for_run`) and
        append their outputs: how many lines, or an awaitable of that while the rest of
        their outputs waits for room (rare: the planner's room changed as it planned)."""
        interpreter, planner = self.interpreter, self.planner
        if self.line_s > 0.0:
            stop = min(stop, start + int(1.25 * planner.room_s() / self.line_s) + 1)
        run = interpreter.read_plain(columns, start, stop)
        if run.ends.shape[0]:  # up to the first move with no room
            moves, seconds = planner.room_for_run(run.ends, *run.move_feeds())
            lines = run.lines_before(moves)
            if not lines:
                return 0
            run = run.head(lines, interpreter.position)
            self.line_s = seconds / lines
        interpreter.commit_plain(run)
        if not run.count:
            return 0
        outputs = run.outputs()
        index = offer_run(planner, outputs)
        if index:
            self._note_input(_RUN)
        if index == len(outputs.outputs):
            return run.count
        return self._feed_run(outputs, index, epoch, run.count)

    async def _feed_run(self, run: MoveRun, index: int, epoch: int, lines: int) -> int:
        """The rest of a run's outputs from ``index`` on, waiting for room (``epoch``: the
        machine's when the run began: motion reset meanwhile refuses the rest); ``lines``."""
        while index < len(run.outputs):
            await self._wait_for_room(epoch)
            taken = offer_run(self.planner, run, index)
            if taken > index:
                self._note_input(_RUN)
            index = taken
        return lines

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

    def _offer(self, outputs: list[Output], index: int) -> int:
        """Offer ``outputs[index:]`` to the planner (:func:`~server.motion.feed.offer`, as
        ``estimate`` does) up to the next sync request or a full planner; in check mode they
        are interpreted, never planned. Returns the index of the first output not taken."""
        if self.check_mode:
            while index < len(outputs) and type(outputs[index]) is not Sync:
                index += 1
            return index
        taken = offer(self.planner, outputs, index)
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
