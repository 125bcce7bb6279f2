"""Stored jobs: play through the dispatcher, progress, abort, suspend (the files themselves:
:mod:`.store`).

Playing a file streams its lines through the same dispatcher a sender uses (:mod:`.player`),
so the job is executed, flow-controlled and error-checked exactly like streamed G-code (its
runs of plain lines read at once, to the same effect); the first line that is refused stops
the job with a message naming the line. A line answered downstream (a Grbl controller) is
deferred by the dispatcher: the job sends on while it is in the controller's buffer and
stops at the first answer that is an error. A job file is never held in memory
whole: it is planned by reading it through in processes of their own (:mod:`.planning`): its
fit before anything moves, its time filled in when known; then its lines are read again as
they are sent.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from server.errors import CommandError, Error
from server.jobs.clock import JobClock, JobPlan
from server.jobs.interjections import Interjections
from server.jobs.planning import JobPlans
from server.jobs.player import send_lines
from server.jobs.reading import Stopped, read_batches
from server.jobs.store import JobStore
from server.motion.moves import Action, ActionName
from server.offline.stats import format_duration
from server.paths import jobs_dir
from server.runtime.dispatcher import Command
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    from server.config import Config
    from server.gcode.interpreter import Interpreter
    from server.machine.machine import Machine
    from server.runtime.clock import Clock
    from server.runtime.dispatcher import Dispatcher
    from server.runtime.events import EventBus
    from server.runtime.state import MachineStatus

log = logging.getLogger("motiond.jobs")


class JobHost(Protocol):
    """What the jobs need of the kernel that owns them (the kernel is one)."""

    config: Config
    clock: Clock
    events: EventBus
    status: MachineStatus
    machine: Machine
    dispatcher: Dispatcher

    @property
    def state(self) -> MachineState: ...

    def push(self, message: str) -> None: ...

    def set_state(self, state: MachineState) -> None: ...


@dataclass(slots=True)
class JobProgress:
    """The current or last job. ``state``: running, paused, done, aborted or failed.

    ``paused_for`` says why a paused job waits (``hold``, ``M0``, ``M1``, ``tool change T2``);
    ``fit`` is the job's extent under the placement it started from (machine mm, per axis)."""

    name: str
    state: str
    lines_total: int = 0
    lines_done: int = 0
    percent: float = 0.0
    elapsed_s: float = 0.0
    remaining_s: float | None = None
    error: str | None = None
    estimate_s: float | None = None
    started_s: float = 0.0
    paused_for: str | None = None
    fit: dict[str, object] | None = None


@dataclass(slots=True)
class _JobSource:
    name: str
    ticket: int  # the stop generation the job started in: its lines carry it
    can_control: bool = True


class Jobs(JobStore):
    """The job files of one kernel and the one job that may play at a time."""

    def __init__(self, kernel: JobHost) -> None:
        super().__init__(jobs_dir(kernel.config.core), kernel.config.core.jobs.max_upload_bytes)
        self.kernel = kernel
        self._task: asyncio.Task[None] | None = None
        self._progress: JobProgress | None = None
        self._clock: JobClock | None = None
        self._plan: JobPlan | None = None  # the current job's
        self._plans = JobPlans(self._timed)
        self._interjections = Interjections()
        kernel.events.subscribe(Event.ACTION, self._on_action)
        kernel.events.subscribe(Event.STOP, self._on_stop)
        dispatcher = kernel.dispatcher
        dispatcher.register("ls", self._ls, when_locked=True, query=True)
        dispatcher.register("play", self._play)
        dispatcher.register_immediate("progress", self._status, query=True)
        for name, handler in (("abort", self._abort), ("suspend", self._suspend),
                              ("resume", self._resume)):
            dispatcher.register_immediate(name, handler)  # a held job holds the stream

    # -- playing ----------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    def is_playing(self) -> bool:
        """A job is streaming (not paused)."""
        return self.running and self._progress is not None and self._progress.state == "running"

    def is_paused(self) -> bool:
        return self._progress is not None and self._progress.state == "paused"

    @property
    def active(self) -> bool:
        """A job is running or paused (not yet done, failed or aborted)."""
        progress = self._progress
        return progress is not None and progress.state in ("running", "paused")

    def interject(self, text: str, ticket: int) -> asyncio.Future[list[str] | None] | None:
        """Run ``text`` as part of the running or paused job, before its next line, in order
        with its motion (see :mod:`.interjections`); ``ticket``: the stop generation it was
        asked in. None: no job plays (nothing queued). The future's ``None``: the job ended
        first and the line did not run. Raises CommandError 45 when too many lines wait."""
        if not (self.running and self.active):
            return None
        return self._interjections.add(text, ticket)

    async def start(self, name: str, ticket: int | None = None) -> JobProgress:
        """Check a stored file against the machine as it is now, then play it (``job.start``,
        ``play``, MQTT ``cmd/job``). ``ticket``: the stop generation the start was asked in
        (default now): a stop while the file is checked ends the check, and the job never
        starts.

        Raises:
            CommandError: 47 (the job does not fit the travel from the current work origin:
                the message names each axis, by how much, and where the origin would have to
                be), 45 busy or stopped meanwhile, 44 no such file. Nothing moves.
        """
        status = self.kernel.status
        ticket = status.ticket() if ticket is None else ticket
        path = self._playable(name)
        plan = await self.plan(name)
        if not status.still_valid(ticket):
            raise CommandError(Error.BUSY, f"{path.name}: a stop came while it was checked")
        if not plan.fit.fits:
            raise CommandError(Error.JOB_DOES_NOT_FIT, f"{path.name}: {plan.fit.describe()}")
        self.play(name, plan, ticket)
        assert self._progress is not None
        return self._progress

    async def plan(self, name: str) -> JobPlan:
        """What the stored file ``name`` would do from the machine as it is now: extent under
        the current placement and fit, its time filled in when known (see
        :class:`~server.jobs.planning.JobPlans`: recent plans are kept while neither the
        file nor the machine's state changes). Raises CommandError 44, or 45 when a stop
        came while it was read."""
        path = self.path(name)
        interpreter = self.kernel.machine.new_interpreter(soft_limits=False, live=True)
        try:
            stat = await asyncio.to_thread(path.stat)
        except OSError as exc:
            message = f"cannot read {path.name}: {exc.strerror}"
            raise CommandError(Error.FILE_ERROR, message) from exc
        key = (stat.st_size, stat.st_mtime_ns, interpreter.state_key())
        return await self._make_plan(path, interpreter, key, stat.st_size)

    async def _make_plan(
        self, path: Path, interpreter: Interpreter, key: object, size_bytes: int
    ) -> JobPlan:
        core = self.kernel.config.core
        try:
            return await self._plans.plan(path, core, interpreter, key, size_bytes)
        except OSError as exc:
            message = f"cannot read {path.name}: {exc.strerror}"
            raise CommandError(Error.FILE_ERROR, message) from exc
        except Stopped as exc:
            message = f"{path.name}: stopped while it was being checked"
            raise CommandError(Error.BUSY, message) from exc

    def _timed(self, plan: JobPlan) -> None:
        """A plan's time came: the job playing from it shows its estimate from now on."""
        progress, clock = self._progress, self._clock
        if plan is self._plan and progress is not None and self.active:
            if clock is not None:
                clock.timing = plan.timing
            progress.estimate_s = plan.duration_s
            self._announce()

    def _playable(self, name: str) -> Path:
        """A job starts only on an idle machine nobody else is using (every path: ``play``,
        the JSON API, MQTT): a sender's stream is never cut by a job (error 45)."""
        if self.running:
            raise CommandError(Error.BUSY, "a job is already running; abort it first")
        state = self.kernel.state
        if state is not MachineState.IDLE:
            raise CommandError(Error.BUSY, f"cannot start a job in state {state.value}")
        if self.kernel.machine.busy:
            raise CommandError(Error.BUSY, "cannot start a job while motion is queued")
        path = self.path(name)
        if not path.is_file():
            raise CommandError(Error.FILE_ERROR, f"no job file {path.name}")
        return path

    def play(self, name: str, plan: JobPlan | None = None, ticket: int | None = None) -> None:
        """Start playing a stored file; with ``plan`` (from :meth:`start`) when it was made
        from the machine as it still is, else the job plans (and checks its fit) first.
        Every line of the job carries ``ticket`` (default now): after a stop, none runs."""
        status = self.kernel.status
        ticket = status.ticket() if ticket is None else ticket
        if not status.still_valid(ticket):
            raise CommandError(Error.BUSY, f"{name}: a stop came before it started")
        path = self._playable(name)
        interpreter = self.kernel.machine.interpreter
        if plan is not None and plan.placement != (interpreter.position, interpreter.wco()):
            raise CommandError(Error.BUSY, "the machine moved while the job was being checked")
        self._progress = JobProgress(path.name, "running", started_s=self.kernel.clock.now_s())
        self._clock, self._plan = None, plan
        if plan is not None:
            self._planned(self._progress, plan)
        source = _JobSource(f"job:{path.name}", ticket)
        self.kernel.dispatcher.claim(source)  # other connections may query, hold and stop
        self._task = asyncio.get_running_loop().create_task(
            self._run(path, self._progress, source, plan), name=f"job:{path.name}"
        )
        self._announce()

    def abort(self, reason: str = "job aborted") -> None:
        """Stop the job and all motion at once; tools off. A stop: what anyone asked for
        before it is void (a baby-step waiting for the job, a script between its lines)."""
        progress = self._progress
        if progress is not None and progress.state in ("running", "paused"):
            progress.state, progress.remaining_s, progress.paused_for = "aborted", None, None
        self._plans.cancel()
        self.kernel.machine.quickstop(reason)
        self.kernel.status.stop(reason)
        if self._task is not None:
            self._task.cancel()
        self._announce()

    def _on_stop(self, reason: str) -> None:
        """A stop ends the plans being read (their processes are killed at once); a job
        playing meets the stop at its next line (its ticket is void)."""
        self._plans.cancel()

    def suspend(self) -> None:
        if self.running and self._progress is not None:
            self.kernel.machine.feed_hold()
            self._pause("hold")

    def resume(self) -> None:
        """Continue a paused job: after a hold, an M0/M1 or a tool change (cycle start)."""
        if self._progress is not None and self._progress.state == "paused":
            self.kernel.machine.cycle_start()
            self._progress.state, self._progress.paused_for = "running", None
            self._announce()

    def _pause(self, reason: str) -> None:
        if self._progress is not None:
            self._progress.state, self._progress.paused_for = "paused", reason
            self._announce()

    def _on_action(self, action: Action) -> None:
        """Motion reached M0/M1 (the machine holds) or M6 (held here): the job waits for
        ``resume`` (``~``, the UI's Continue), saying why."""
        if not self.is_playing():
            return
        if action.name == ActionName.PAUSE:
            self._pause("M1" if action.params.get("optional") else "M0")
        elif action.name == ActionName.TOOL_CHANGE:
            machine = self.kernel.machine
            machine.stepgen.hold()
            self.kernel.set_state(MachineState.HOLD)
            tool = action.params.get("tool")
            self.kernel.push(f"[MSG:Tool change: insert T{tool}, then resume (~)]")
            self._pause(f"tool change T{tool}")

    def progress(self) -> JobProgress | None:
        """The current or last job, with times brought up to date."""
        progress = self._progress
        if progress is not None and progress.state in ("running", "paused"):
            progress.elapsed_s = self.kernel.clock.now_s() - progress.started_s
            if self._clock is not None:
                machine = self.kernel.machine
                progress.remaining_s = self._clock.remaining_s(
                    machine.stepgen.state, machine.feed_override)
        return progress

    async def close(self) -> None:
        """Stop the player task and the plans being read (shutdown)."""
        await self._plans.close()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def _run(
        self, path: Path, progress: JobProgress, source: _JobSource, plan: JobPlan | None
    ) -> None:
        try:
            core = self.kernel.config.core
            if plan is None:
                interpreter = self.kernel.machine.new_interpreter(soft_limits=False, live=True)
                size = (await asyncio.to_thread(path.stat)).st_size
                plan = self._plan = await self._make_plan(path, interpreter, object(), size)
            self._planned(progress, plan)
            if not plan.fit.fits:
                self._fail(progress, plan.fit.describe())  # before any line: nothing moved
                return
            machine = self.kernel.machine
            self._clock = JobClock(plan.timing, machine.stepgen.state,
                                   counts_blocks=machine.counts_blocks)
            async with contextlib.aclosing(
                read_batches(path, core.protocol.line_limit)
            ) as batches:
                await self._stream(batches, progress, source)
        except OSError as exc:
            self._fail(progress, f"cannot read {path.name}: {exc.strerror}")
        except CommandError as exc:  # the plan: the file went, or a stop came
            alarm = self.kernel.state is MachineState.ALARM
            self._fail(progress, "line 1: stopped by an alarm while it was being checked"
                       if alarm else f"error:{exc.code} {exc.message}")
        finally:
            self._interjections.release()  # the job is over: what waits did not run

    async def _stream(
        self, batches: AsyncIterator[list[str]], progress: JobProgress, source: _JobSource
    ) -> None:
        machine = self.kernel.machine
        failure = await send_lines(batches, progress, source, self.kernel.dispatcher,
                                   lambda: machine.interpreter, self.kernel.config.core,
                                   self._interjections)
        if failure is not None:
            if self.kernel.state is MachineState.ALARM and f": error:{Error.BUSY} " in failure:
                # a line refused because the alarm's stop came after it was sent: the alarm
                failure = f"{failure.partition(':')[0]}: stopped by an alarm"
            self._fail(progress, failure)
            return
        await machine.wait_idle()
        if self.kernel.state is MachineState.ALARM:
            self._fail(progress, f"line {progress.lines_done}: stopped by an alarm")
            return
        self.progress()  # its times up to now, while it still counts as running
        progress.state, progress.percent = "done", 100.0
        progress.remaining_s = 0.0
        self.kernel.push(f"[MSG:job {progress.name} done in {format_duration(progress.elapsed_s)}]")
        self._announce()

    def _planned(self, progress: JobProgress, plan: JobPlan) -> None:
        progress.fit = plan.fit.as_dict(self.kernel.config.core.axis_names)
        progress.estimate_s = progress.remaining_s = plan.duration_s  # None until known
        progress.lines_total = plan.lines

    def _fail(self, progress: JobProgress, message: str) -> None:
        progress.state, progress.error = "failed", message
        progress.remaining_s = progress.paused_for = None
        log.warning("job %s stopped at %s", progress.name, message)
        self.kernel.push(f"[MSG:job {progress.name} stopped at {message}]")
        self._announce()

    def _announce(self) -> None:
        self.kernel.events.emit(Event.JOB, self.progress())

    # -- Smoothie commands ------------------------------------------------------------------
    def _ls(self, command: Command) -> list[str]:
        sizes = "-s" in command.args
        return [
            f"{'./' if f.name.lower().startswith('ok') else ''}{f.name}"
            + (f" {f.size_bytes}" if sizes else "")
            for f in self.files()
        ]

    async def _play(self, command: Command) -> list[str]:
        name = command.args.split()[0] if command.args.split() else ""
        try:
            progress = await self.start(name, command.ticket)
        except CommandError as exc:
            if exc.code == Error.JOB_DOES_NOT_FIT:  # a Grbl sender sees only error:47
                self.kernel.push(f"[MSG:{exc.message}]")
            raise
        return [f"[MSG:Playing {progress.name}]"]

    def _status(self, command: Command) -> list[str]:
        progress = self.progress()
        if progress is None or progress.state not in ("running", "paused"):
            return ["[MSG:Not currently playing]"]
        remaining = progress.remaining_s
        return [
            f"[MSG:file: {progress.name}, {progress.percent:.0f} % complete, elapsed time: "
            f"{_clock(progress.elapsed_s)}, est time: "
            f"{'-' if remaining is None else _clock(remaining)}]"
        ]

    def _abort(self, command: Command) -> list[str]:
        self.abort()
        return ["[MSG:Aborted playing or paused file]"]

    def _suspend(self, command: Command) -> None:
        self.suspend()

    def _resume(self, command: Command) -> None:
        self.resume()


def _clock(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}"


