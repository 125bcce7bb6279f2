"""``[backend] kind = "grbl"``: the machine is a Grbl, grblHAL or FluidNC controller downstream.

:class:`GrblMachine` is the :class:`~server.machine.machine.Machine` of such a setup. motiond's
whole front stays as it is (transports, protocol, dispatcher, jobs, API); only the end of the
pipeline changes. Every G-code line still goes through the dispatcher and motiond's interpreter
(one path per line: bad lines fail here with motiond's error numbers, soft limits and modal
state are checked), but instead of being planned and stepped it is sent to the controller,
compacted, with character counting (:class:`~server.backends.grbl.controller.Controller`). The
line's reply is deferred (:attr:`Command.defer <server.runtime.dispatcher.Command>`): it is the
controller's ``ok`` or ``error:N``, sent to the client once the controller has answered, in
order, while the following lines already stream.

Realtime commands reach this machine through :class:`~server.kernel.control.MachineControl`
as on any backend and are written to the controller at once. The controller's status, polled
at ``[backend] status_hz`` by one task, is the machine's: it drives the state, the position the
web UI and ``M114`` show, and every client's ``?`` report (answered from the latest report, so
ten clients polling do not multiply the traffic to the board). The controller's ``$$`` settings
are adopted into motiond's machine model at each connection (a warning per difference with the
config), so ``estimate``, soft limits and the toolpath agree with the real machine.

An alarm from the controller (``ALARM:N``) alarms motiond, which tells every client. An alarm
raised by motiond (soft limit, M112, a lost connection) stops the controller with Ctrl-X. A lost
connection alarms (ALARM:42), fails the lines in flight, stops a job, and the controller is
reopened every ``reconnect_s``; ``$X`` unlocks both once it is back.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial

from server.backends.grbl.adopt import adopt_offsets, adopt_settings, adopt_space
from server.backends.grbl.answers import (
    an_answer,
    axes_of,
    controller_error,
    front_buffer,
    mixed_line_error,
    overrides_bytes,
)
from server.backends.grbl.babystep import babystep_lines, is_babystep
from server.backends.grbl.controller import Controller, Handshake, LineDropped
from server.backends.grbl.feedback import FeedbackGate, clean_reply
from server.backends.grbl.journal import Sent, SentLines
from server.backends.grbl.link import Answered, compact
from server.backends.grbl.reports import ControllerStatus
from server.config import Config
from server.errors import ALARM_MEANINGS, Alarm, CommandError, Error
from server.gcode.parser import Line, parse_line
from server.machine.machine import Machine
from server.motion.backend import Backend
from server.motion.motion_state import HoldState
from server.motion.moves import Move, Output, Sync, SyncKind, ToolMode
from server.protocol.events import Realtime
from server.protocol.reports import UNLOCK_HINT, StatusSnapshot
from server.runtime.clock import Clock
from server.runtime.dispatcher import Command, Dispatcher
from server.runtime.events import EventBus, MachineState
from server.runtime.state import MachineStatus

log = logging.getLogger("motiond.grbl")
CAUTION_UNLOCKED = "[MSG:Caution: Unlocked]"
LOCAL_SYNCS = frozenset({SyncKind.HALT, SyncKind.CLEAR_HALT, SyncKind.MESSAGE,
                         SyncKind.REPORT_POSITION, SyncKind.WAIT, SyncKind.QUICKSTOP})
# M112, M999, messages, M114, M400, M410: motiond's own, on a line of their own (Grbl has none
# of them: error 20 for a line that mixes one with anything for the board; but a stop on a line
# stops, whatever else the line says).
LOCAL_M_CODES = frozenset({105.0, 114.0, 115.0, 400.0, 999.0})
STOPS = frozenset({SyncKind.HALT, SyncKind.QUICKSTOP})
_STATES = {"Idle": MachineState.IDLE, "Run": MachineState.RUN, "Hold": MachineState.HOLD,
           "Jog": MachineState.JOG, "Home": MachineState.HOME, "Door": MachineState.DOOR,
           "Sleep": MachineState.SLEEP, "Check": MachineState.CHECK,
           "Tool": MachineState.HOLD}  # grblHAL's M6: held until a cycle start (~)
_MOVING = frozenset({"Run", "Jog", "Home"})
_STILL = frozenset({"Idle", "Alarm", "Check", "Sleep"})  # nothing will move without a command
Edit = Callable[[list[str]], list[str]]


class GrblMachine(Machine):
    """The motion pipeline ends at a Grbl controller; see the module docstring."""

    counts_blocks = False  # the board executes the blocks: only its reports are known
    reads_spans = False  # every line goes to the board as it was written

    def __init__(self, config: Config, clock: Clock, events: EventBus, status: MachineStatus,
                 backend: Backend) -> None:
        super().__init__(config, clock, events, status, backend)
        self.controller = Controller(config.core.backend, self)
        self.controller_status: ControllerStatus | None = None
        self._controller_alarm = False  # the alarm in force came from the controller
        self._previous_state = ""
        self._position_synced = False
        self._overrides = (100, 100, 100)  # Grbl reports Ov: only now and then
        self._accessories = ""  # and A: only beside Ov:
        self._idle = asyncio.Event()
        self._idle.set()
        self._feedback = FeedbackGate(clock.now_s())
        self._board_settings: dict[int, float] = {}  # $$ at the connection, then $x= sent
        self._explicit_limits = "soft_limits" in self._defaults.machine.model_fields_set
        self._sent = SentLines(lambda: self.interpreter)  # lines the board may still refuse
        self.board_axes = len(config.core.axis_names)  # the board's, once it has told

    # -- lines ------------------------------------------------------------------------------
    async def handle_gcode(self, command: Command) -> list[str]:
        line = command.line
        assert line is not None
        await self._requeried()
        words = [letter for letter, value in line.words if letter != "N"]
        codes = [value for letter, value in line.words
                 if letter == "M" and value in LOCAL_M_CODES]
        if len(words) > 1 and codes and not self.check_mode:
            raise mixed_line_error(max(codes))  # refused as the board refuses these codes, first
        if is_babystep(line) and not self.check_mode:  # Grbl does not know M290
            return await self._babystep(command, line)
        before = self.interpreter.save()
        outputs = self.interpret(command)
        syncs = [out for out in outputs if type(out) is Sync]
        local = [sync for sync in syncs if sync.kind in LOCAL_SYNCS]
        if local and not self.check_mode and (
                len(local) < len(outputs) or self.interpreter.save() != before):
            self.interpreter.restore(before)  # nothing of it reaches the board
            if not any(sync.kind in STOPS for sync in local):
                raise mixed_line_error(0.0)  # a module's local code: the same as above
            syncs = local  # a stop on the line wins: M112, M410 act, the rest is dropped
        if self.check_mode or local:
            messages: list[str] = []
            for sync in syncs:
                if not self.check_mode or sync.kind is SyncKind.MESSAGE:
                    messages += await self.sync(sync)
            return messages
        sent = self._sent.add(before, lambda: self.interpreter.execute(line))
        if any(sync.kind is SyncKind.PROBE for sync in syncs):
            return await self._probe(command, sent)
        motion = any(isinstance(out, Move) for out in outputs)
        return await self.forward(compact(command.text), command, motion=motion, sent=sent)

    async def _babystep(self, command: Command, line: Line) -> list[str]:
        """``M290`` as :func:`~server.backends.grbl.babystep.babystep_lines`: read once every
        line before is answered (motiond's state is then the board's), each line sent once the
        one before is accepted, the reply their answers; a refusal undoes it (the journal)."""
        epoch = self.epoch
        await self.controller.answered_all()
        if epoch != self.epoch:
            raise CommandError(Error.BUSY, "not run: motion was reset while M290 waited")
        before = self.interpreter.save()
        self.interpret(command)
        try:
            texts = babystep_lines(line, self.interpreter)
        except CommandError:
            self.interpreter.restore(before)
            raise
        sent = self._sent.add(before, lambda: self.interpreter.execute(line))
        alone, messages = replace(command, defer=None), []
        try:
            for text in texts:
                messages += await self.forward(text, alone, motion=text.startswith("G53"))
        except CommandError:
            self._sent.refused(sent)
            raise
        self._sent.answered(sent)
        return messages

    async def _probe(self, command: Command, sent: Sent) -> list[str]:
        """G38.x: the board probes; motiond waits for it (Grbl's parser does too), then takes
        the position it stopped at."""
        messages = await self.forward(compact(command.text), replace(command, defer=None),
                                      motion=True, sent=sent)
        await self.wait_idle()
        self.interpreter.set_position(self.stepgen.state.position_mm)
        return messages

    async def forward(self, text: str, command: Command, *, motion: bool = False,
                      sent: Sent | None = None, edit: Edit | None = None) -> list[str]:
        """Send one line to the controller; its reply is deferred when the caller allows.
        Only a ``motion`` line makes the machine busy (Run, its sender the owner) until the
        board reports it done; ``$X``, ``G21`` or ``M5`` leave it as the board has it.
        ``sent``: the line's entry in the journal (undone if the board refuses the line);
        ``edit``: what to change in the board's messages before the client sees them."""
        if not text:
            return []
        epoch = self.epoch
        try:
            answer = await self.controller.send_line(
                text, lambda: epoch == self.epoch, motion=motion)
        except LineDropped as exc:
            if sent is not None:
                self._sent.refused(sent)
            raise CommandError(Error.BUSY, str(exc)) from exc
        if motion:
            self._idle.clear()
            self.idle_event.clear()
            if self.status.state is MachineState.IDLE:
                self.status.set_state(MachineState.RUN)
        reply: asyncio.Future[list[str]] = asyncio.get_running_loop().create_future()
        answer.add_done_callback(lambda done: self._settle(done, reply, text, sent, edit))
        if command.defer is not None:
            command.defer(reply)
            return []
        return await reply

    async def _forward_command(self, command: Command) -> list[str]:
        """``$X``, ``$H``: after motiond's own handler (which checks the line), the
        controller's turn."""
        self._controller_alarm = False
        try:
            if command.name == "$X":  # motiond's own unlock said it already: said once
                messages = await self.forward(compact(command.text), replace(command, defer=None))
                return [text for text in messages if text != CAUTION_UNLOCKED]
            return await self.forward(compact(command.text), command, motion=True)
        except CommandError:
            if command.name == "$X" and not self.controller.ready:  # nothing to unlock yet
                self.status.alarm(Alarm.BACKEND_FAILED, "the controller is not connected")
            raise

    async def write_setting(self, command: Command) -> list[str]:
        """``$x=value`` is the board's to judge (``$22=1`` included): sent first; once it
        accepts, motiond adopts it as at a connection (travel, soft limits, rates...)."""
        number, _, value = command.args.partition("=")
        messages = await self.forward(compact(command.text), replace(command, defer=None))
        try:
            board = {int(number): float(value)}
        except ValueError:
            return messages  # the board took what motiond cannot read: nothing to adopt
        self._board_settings.update(board)
        adopt_settings(self.settings, board, len(self.core.axis_names))
        adopt_space(self.core, self._board_settings, keep_soft_limits=self._explicit_limits)
        self.apply_settings()
        return messages

    async def board_answer(self, command: Command) -> list[str] | None:
        """``$$``, ``$#``, ``$G``, ``$I``, ``$N``: the board's own answer, line for line
        (``$I``'s receive buffer is the front's, which a sender fills); ``$N0=``/``$N1=``:
        read by motiond's interpreter as Grbl runs the line it stores, then the board's.
        None (motiond answers) while the board is not connected, or in check mode."""
        if not self.controller.ready or self.check_mode:
            return None
        if command.name in ("$N0=", "$N1="):
            line = parse_line(command.args)
            if line.error is not None:
                raise line.error
            return await self._interpreted(command, lambda: self.interpreter.execute(line))
        edit = (partial(front_buffer, front_bytes=self.core.protocol.rx_buffer_bytes)
                if command.name == "$I" else None)
        return await self.forward(compact(command.text), command, edit=edit)

    async def jog(self, command: Command, line: Line) -> None:
        """``$J=``: checked by motiond's interpreter (which moves to its target), then the
        board's; a jog the board refuses leaves motiond where it was."""
        await self._interpreted(command, lambda: self.interpreter.jog(line), motion=True)

    async def _interpreted(self, command: Command, read: Callable[[], Sequence[Output]], *,
                           motion: bool = False) -> list[str]:
        await self._requeried()
        before = self.interpreter.save()
        outputs = read()
        sent = self._sent.add(before, read)
        motion = motion or any(isinstance(out, Move) for out in outputs)
        return await self.forward(compact(command.text), command, motion=motion, sent=sent)

    async def _requeried(self) -> None:
        """After a reset, lines are read once the board's modes are known again (its start-up
        lines may have changed them)."""
        if not self.controller.requeried.is_set():
            await self.controller.requeried.wait()

    def register_commands(self, dispatcher: Dispatcher) -> None:
        for name in ("$X", "$H"):
            dispatcher.register(name, self._forward_command, when_locked=True)

    async def queue_move(self, move: Move) -> None:
        """Module moves are the controller's: motiond's planner stays empty."""

    async def wait_idle(self) -> None:
        """Until every line sent is answered and the controller reports Idle after that."""
        await self._idle.wait()

    @property
    def lines_undone(self) -> int:
        """Lines motiond had read that the board then refused (and motiond undid)."""
        return self._sent.undone

    @property
    def busy(self) -> bool:
        return not self._idle.is_set()

    # -- the controller's reports (ControllerListener) ---------------------------------------
    def on_connected(self, handshake: Handshake) -> None:
        self.board_axes = handshake.axis_count or len(self.core.axis_names)
        self._board_settings = dict(handshake.settings)
        adopt_settings(self.settings, handshake.settings, len(self.core.axis_names))
        adopt_space(self.core, handshake.settings, keep_soft_limits=self._explicit_limits)
        self.apply_settings()
        adopt_offsets(self.interpreter, self.core.axis_names, handshake)
        self._position_synced = False
        self.status.push(f"[MSG:controller connected: {handshake.banner}]")

    def on_requeried(self, modal: tuple[str, ...], offsets: tuple[str, ...]) -> None:
        """After a reset: the board's modes and offsets (its start-up lines ran) are motiond's."""
        handshake = self.controller.handshake
        if handshake is not None:
            adopt_offsets(self.interpreter, self.core.axis_names,
                          replace(handshake, settings=self._board_settings, offsets=offsets,
                                  modal=modal))

    def on_answer(self) -> None:
        """An answer alone says nothing about motion: the next report does."""

    def on_status(self, report: ControllerStatus) -> None:
        for line in self._feedback.flush(self.clock.now_s()):
            self.status.push(line)
        self.controller_status = report
        if report.overrides is not None:
            self._overrides, self._accessories = report.overrides, report.accessories
        self.feed_override, self.rapid_override, self.spindle_override = self._overrides
        self._publish_motion(report)
        base = report.base_state
        if base == "Alarm":
            if self._previous_state != "Alarm" and self.status.state is not MachineState.ALARM:
                self._controller_alarm = True
                self.status.alarm(Alarm.ABORT_CYCLE,
                                  "the controller is in alarm: $X (or $H) to unlock")
        elif self.status.state not in (MachineState.ALARM, MachineState.CHECK):
            state = _STATES.get(base)
            if state is MachineState.IDLE and self.controller.motion_pending:
                state = MachineState.RUN  # lines with motion are in the board's buffer
            if state is not None:
                self.status.set_state(state)
        self._previous_state = base
        if base in _STILL and not self.controller.motion_pending:
            self._sync_position(report)
            self._idle.set()
            self.idle_event.set()

    def on_alarm(self, code: int) -> None:
        self._controller_alarm = True
        self._previous_state = "Alarm"
        if self.status.state is MachineState.ALARM and self.status.alarm_code == code:
            return
        meaning = ALARM_MEANINGS.get(code, "see the controller's documentation")
        self.status.alarm(code, f"controller ALARM:{code}: {meaning}")

    def on_feedback(self, texts: list[str]) -> None:
        """Lines the board printed on its own: pushed to every client, cleaned and at a
        bounded rate (a summary line counts what was held back)."""
        shown = [text for text in texts  # (an answer: to a line a reset dropped; the unlock
                 if not an_answer(text) and text != UNLOCK_HINT]  # hint: motiond's, sent)
        for line in self._feedback.offer_lines(shown, self.clock.now_s()):
            self.status.push(line)

    def on_lost(self, reason: str) -> None:
        self.controller_status = None
        self._previous_state = ""
        self._controller_alarm = False
        self.status.alarm(Alarm.BACKEND_FAILED, f"controller connection lost: {reason}")
        self._idle.set()
        self.idle_event.set()

    def on_restart(self, banner: str) -> None:
        """The board restarted by itself (reset button, power): what it had is lost."""
        self._position_synced = False
        self._controller_alarm = False
        self.status.alarm(Alarm.BACKEND_FAILED,
                          f"the controller restarted ({banner}): position may be lost")

    def _publish_motion(self, report: ControllerStatus) -> None:
        """The controller's position and speed become motiond's motion state (web UI, M114)."""
        motion = self.stepgen.state
        if report.machine_mm is not None:
            axes = len(self.core.axis_names)
            motion.position_mm = tuple((list(report.machine_mm) + [0.0] * axes)[:axes])
        motion.speed_mm_s = report.feed_mm_min / 60.0
        motion.moving = report.base_state in _MOVING or report.state == "Hold:1"
        motion.hold = {"Hold:0": HoldState.STOPPED, "Hold:1": HoldState.DECELERATING}.get(
            report.state, HoldState.NONE)
        motion.line_number = report.line_number
        motion.s_value = report.spindle_s
        motion.tool_mode = ToolMode.CCW if "C" in report.accessories else (
            ToolMode.CW if "S" in report.accessories else ToolMode.OFF)
        now_s = self.clock.now_s()
        if motion.moving and motion.hold is HoldState.NONE:  # a job's clock runs (job_clock)
            motion.motion_time_s += now_s - motion.time_s
        motion.time_s = now_s

    def _sync_position(self, report: ControllerStatus) -> None:
        """After a connection or a reset, the interpreter starts from where the machine is."""
        if self._position_synced or report.machine_mm is None:
            return
        self._position_synced = True
        self.interpreter.set_position(self.stepgen.state.position_mm)
        self.planner.set_position(self.stepgen.state.position_mm)

    # -- realtime commands ------------------------------------------------------------------
    def realtime(self, command: Realtime) -> None:
        self.controller.realtime(int(command))

    def feed_hold(self) -> None:
        self.controller.realtime(Realtime.HOLD)

    def cycle_start(self) -> None:
        self.controller.realtime(Realtime.RESUME)

    def cancel_jog(self) -> None:
        self.controller.realtime(Realtime.JOG_CANCEL)

    def set_overrides(
        self, feed: int | None = None, rapid: int | None = None, spindle: int | None = None
    ) -> None:
        """The API's override setter, as the realtime bytes Grbl knows (100 %, then ±10s and
        ±1s); the board's next report confirms them."""
        for byte in overrides_bytes(feed, rapid, spindle):
            self.controller.realtime(byte)
        self.feed_override = self.feed_override if feed is None else max(10, min(200, feed))
        self.spindle_override = (
            self.spindle_override if spindle is None else max(10, min(200, spindle)))
        self.rapid_override = self.rapid_override if rapid is None else rapid

    def soft_reset(self) -> None:
        """Ctrl-X: the board resets its overrides and turns its tools off; so does the front
        until the board's next report says otherwise."""
        self._controller_alarm = False
        super().soft_reset()
        self._overrides, self._accessories = (100, 100, 100), ""

    def stop_now(self) -> None:
        """Stop the controller (Ctrl-X) unless the alarm is its own; lines in flight fail."""
        self.epoch += 1
        self._sent.clear()  # the board's buffer is emptied; the interpreter resynchronised
        if not self._controller_alarm:
            self.controller.reset()
        self._position_synced = False
        self.room.set()

    def status_snapshot(self, rx_free_bytes: int) -> StatusSnapshot | None:
        """The controller's latest report as every client's ``?`` answer (None: disconnected)."""
        report = self.controller_status
        if report is None:
            return None
        motion = self.stepgen.state
        axes = self.board_axes
        machine = report.machine_mm or motion.position_mm
        wco = report.wco_mm or self.controller.link.wco_mm or self.interpreter.wco()
        state = "Alarm" if self.status.state is MachineState.ALARM else report.state
        if state == "Idle" and self.controller.motion_pending:
            state = "Run"  # the board has not started (or not reported) the motion sent
        return StatusSnapshot(
            state=state,
            machine_mm=axes_of(machine, axes),
            wco_mm=axes_of(wco, axes),
            feed_mm_s=motion.speed_mm_s,
            spindle_s=report.spindle_s,
            planner_free_blocks=report.planner_free_blocks or 0,
            rx_free_bytes=rx_free_bytes,
            line_number=report.line_number,
            pins=report.pins,
            overrides=self._overrides,
            accessories=self._accessories,
        )

    def _settle(self, answer: asyncio.Future[Answered], reply: asyncio.Future[list[str]],
                text: str, sent: Sent | None, edit: Edit | None) -> None:
        """The controller's answer becomes the line's reply (messages, or a CommandError); a
        refusal is also told to every client (observers see why a job stopped), and undone in
        motiond's interpreter as the board did not run it."""
        error: BaseException | None = (
            LineDropped("cancelled") if answer.cancelled() else answer.exception())
        if sent is not None:
            if error is None and answer.result().error is None:
                self._sent.answered(sent)
            else:
                self._sent.refused(sent)
        if reply.done():
            return
        if isinstance(error, LineDropped):
            reply.set_exception(CommandError(Error.BUSY, f"not run: {error}"))
        elif error is not None:
            reply.set_exception(error)
        elif answer.result().error is None:
            messages = [clean_reply(text) for text in answer.result().messages]
            reply.set_result(edit(messages) if edit is not None else messages)
        else:
            code = answer.result().error
            assert code is not None
            self.status.push(f"[MSG:controller error:{code} on {text}]")
            reply.set_exception(controller_error(code, text))
        reply.exception()  # retrieved here: a caller gone since (a reset) must not log it

    # -- the task ---------------------------------------------------------------------------
    async def run(self) -> None:
        """The controller connection (no step generator: the controller steps)."""
        try:
            await self.controller.run()
        finally:
            self.backend.close()
