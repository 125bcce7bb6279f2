"""A job's plan made in a process of its own: the server's event loop never waits for it.

Reading a big job through the pipeline is seconds of Python; in a thread it would hold the
interpreter lock against the event loop (the operator's ``?`` took 12-30 ms during the plan
of a 10 MB raster). So a plan (:func:`~server.jobs.clock.read_plan`, and the fit alone,
:func:`~server.jobs.clock.read_fit`) is read in a child process forked from a ``forkserver``
that has the pipeline imported already (a fork costs milliseconds, not an interpreter's
start-up), and sends its one result back through a pipe. The children run at ordinary
priority (``motiond serve``'s loop runs at real-time priority where allowed, and a niced plan
starves on a busy host: at nice 10, with two CPU-bound programs on a 2-core host, the
2,000,000-line job of ``benchmarks plan`` was ready in 38 s, not 7.5, and timed in 103, not
15; on an idle host it brought a ``?`` client on the same host from a p99 of 4 ms to 1).
A stop, an abort or the server's shutdown kills the child at once
(:meth:`PlanProcess.cancel`); a child whose server is gone stops by itself within a chunk of
the file (:data:`~server.offline.estimate.READ_CHUNK_CHARS`). Memory in the child
is bounded as the plan's is (the file is read as the plan goes). The plans read one at a time
(files of at most :data:`FIT_FIRST_BYTES`) go to one such child kept between them, the
:class:`PlanWorker`: read warm, at a third of a fresh child's CPU.

The interpreter sent to the child is a copy whose module codes are stand-ins
(:meth:`~server.gcode.codes.CodeTable.stand_ins`): a module's state stays in the server.
"""

from __future__ import annotations

import asyncio
import copy
import errno
import gc
import logging
import multiprocessing
import os
import threading
from collections.abc import Callable, Coroutine
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Generic, TypeVar

from server.config import CoreConfig
from server.gcode.interpreter import Interpreter
from server.jobs.clock import JobPlan, read_fit, read_plan
from server.jobs.reading import Stopped

log = logging.getLogger("motiond.jobs")
TIMING_GRACE_S = 0.2  # the fit waits this long for the time, which a small job has by then
IN_THREAD_BYTES = 16_384  # a file this small is planned in a thread, in one pass (<10 ms)
WORKER_IDLE_S = 60.0  # the plan worker ends after this long without a plan (its ~40 MB)
KEPT_PLANS = 4  # job plans kept for files whose plan may be asked again (bounded memory each)
FIT_FIRST_BYTES = 512 * 1024  # a bigger file's fit is read alone too (see JobPlans)
CONTEXT = multiprocessing.get_context("forkserver")
# What every child would import otherwise, once in the fork server: the main module (the
# ``motiond`` script imports the whole server: 40 ms of CPU a child), numpy.ma (np.unique's
# first call imports it: 12 ms a child)
CONTEXT.set_forkserver_preload(["__main__", "server.jobs.clock", "server.jobs.planning",
                                "numpy.ma"])
T = TypeVar("T")
Reader = Callable[[Path, CoreConfig, Interpreter, Callable[[], bool]], T]


class PlanProcess(Generic[T]):
    """A plan (``reader``: :func:`read_plan`, or :func:`read_fit` alone) read in a
    child process; :meth:`result` waits for it, :meth:`cancel` ends it at once."""

    def __init__(self, reader: Reader[T], path: Path, core: CoreConfig,
                 interpreter: Interpreter) -> None:
        """Nothing runs until :meth:`start`."""
        self._receive, send = CONTEXT.Pipe(duplex=False)
        self._process = CONTEXT.Process(
            target=_child, args=(send, reader, path, core, _portable(interpreter)), daemon=True,
            name=f"plan {path.name}")
        self._send = send
        self._cancelled = False
        self._started: asyncio.Future[None] | None = None

    def start(self) -> None:
        """Start the child (in a thread: the first start launches the fork server)."""
        if self._started is None:
            self._started = asyncio.ensure_future(asyncio.to_thread(self._start))

    async def result(self) -> T | None:
        """The reader's result, or None when cancelled first. Raises what the reader raised
        (OSError: the file cannot be read)."""
        self.start()
        assert self._started is not None
        try:
            await asyncio.shield(self._started)
            if self._cancelled:
                return None
            await _readable(self._receive)  # (no thread waits: the executor's are few)
            answer = await asyncio.to_thread(_receive, self._receive)
        finally:
            self.cancel()
        if answer is None:
            return None  # killed: cancelled, or it died
        kind, value = answer
        if kind == "error":
            raise value
        return value  # type: ignore[no-any-return]

    def cancel(self) -> None:
        """End the child at once (harmless when it has ended, or not started yet)."""
        self._cancelled = True
        if self._started is not None and not self._started.done():
            self._started.add_done_callback(lambda _: self._kill())
        else:
            self._kill()

    def _start(self) -> None:
        try:
            if not self._cancelled:
                self._process.start()
        finally:
            self._send.close()  # the child holds its end: its death is the pipe's end

    def _kill(self) -> None:
        process = self._process
        if process.pid is not None and process.exitcode is None:
            process.kill()


async def _readable(connection: Connection) -> None:
    """Until the child has written (or died: the end of the pipe is readable too)."""
    loop = asyncio.get_running_loop()
    ready: asyncio.Future[None] = loop.create_future()
    descriptor = connection.fileno()

    def wake() -> None:
        if not ready.done():
            ready.set_result(None)

    loop.add_reader(descriptor, wake)
    try:
        await ready
    finally:
        loop.remove_reader(descriptor)


def _portable(interpreter: Interpreter) -> Interpreter:
    """What a planning process is sent: a copy of the caller's own copy whose module codes are
    stand-ins (a module's state stays in the server)."""
    portable = copy.copy(interpreter)
    portable.codes = interpreter.codes.stand_ins()
    return portable


def _receive(connection: Connection) -> tuple[str, Any] | None:
    """The child's one message, or None when it died first (in a thread); the pipe closed."""
    try:
        return _answer(connection)
    finally:
        connection.close()


def _child(send: Connection, reader: Reader[Any], path: Path, core: CoreConfig,
           interpreter: Interpreter) -> None:
    """The planning process: read, send the result (or the error), exit."""
    gc.disable()  # the pipeline makes no reference cycles (see server.cli.offline)
    parent = os.getppid()
    answer = _read(reader, path, core, interpreter, lambda: os.getppid() != parent)
    if answer is not None:
        send.send(answer)
    send.close()


def _read(reader: Reader[Any], path: Path, core: CoreConfig, interpreter: Interpreter,
          stopped: Callable[[], bool]) -> tuple[str, Any] | None:
    """A planning process's answer: ("ok", the result) or ("error", what it raised); None
    when ``stopped()`` ended it (the server is gone)."""
    try:
        return ("ok", reader(path, core, interpreter, stopped))
    except Stopped:
        return None
    except Exception as exc:  # noqa: BLE001 - the server raises it where it waits
        return ("error", exc)


class PlanWorker:
    """One planning process kept between plans, reading one at a time (see :class:`JobPlans`).

    A fresh child of the fork server first writes to every page it touches (copied from the
    fork server's) and starts with cold caches: a 2,400-line raster's plan costs it about
    three times the CPU of the same plan read again in a process that has read one before
    (30 against 10 ms here), and a small job's plan in a thread of the server twice as much as
    here, holding the interpreter lock against the event loop. Started with its first plan
    (in a thread: the first start launches the fork server); a plan cancelled while it reads
    kills it at once (the next plan starts another). Between plans it waits on its pipe, no
    CPU; it ends when the server does (the pipe closes), at :meth:`close`, or after
    :data:`WORKER_IDLE_S` without a plan (its memory, ~40 MB here of which ~30 its own, goes
    back to the host). Its memory is what the largest plan it read needed (files of at most
    :data:`FIT_FIRST_BYTES`) beside the fork server's pages it wrote to."""

    def __init__(self, idle_s: float = WORKER_IDLE_S) -> None:
        self.idle_s = idle_s
        self._process: multiprocessing.process.BaseProcess | None = None
        self._connection: Connection | None = None
        self.busy = False

    @property
    def running(self) -> bool:
        """Whether its process is there (started, not ended: idle, reading, or warm from
        the plans it read)."""
        return self._process is not None and self._process.exitcode is None

    def plan(self, reader: Reader[T], path: Path, core: CoreConfig,
             interpreter: Interpreter) -> WorkerPlan[T]:
        """A plan for this worker to read when it is free (:meth:`WorkerPlan.result`)."""
        return WorkerPlan(self, reader, path, core, interpreter)

    def connection(self) -> Connection:
        """The pipe to the process, started first if it is not running (in a thread)."""
        if self._connection is not None and self.running:
            return self._connection
        self.close()
        ours, theirs = CONTEXT.Pipe()
        process = CONTEXT.Process(target=_serve, args=(theirs, self.idle_s), daemon=True,
                                  name="motiond plans")
        try:
            process.start()
        finally:
            theirs.close()  # the process holds its end: its death is the pipe's end
        self._process, self._connection = process, ours
        return ours

    def kill(self) -> None:
        """End the process at once (a plan it reads is no longer wanted)."""
        process, self._process = self._process, None
        if process is not None and process.exitcode is None:
            process.kill()

    def close(self) -> None:
        """End the process and close the pipe (the server's shutdown; harmless when done)."""
        self.kill()
        connection, self._connection = self._connection, None
        if connection is not None:
            connection.close()


class WorkerPlan(Generic[T]):
    """A plan read by the :class:`PlanWorker` (the interface of :class:`PlanProcess`)."""

    def __init__(self, worker: PlanWorker, reader: Reader[T], path: Path, core: CoreConfig,
                 interpreter: Interpreter) -> None:
        self._request = (reader, path, core, _portable(interpreter))
        self._worker = worker
        self._cancelled = self._reading = False

    async def result(self) -> T | None:
        """The reader's result, or None when cancelled first. Raises what the reader raised;
        OSError when the process ended before it answered (twice: once it may, having been
        idle too long as it was asked); RuntimeError when the worker reads another plan."""
        worker = self._worker
        if worker.busy:
            raise RuntimeError("the plan worker reads one plan at a time")
        worker.busy = True
        try:
            answer = await self._ask()
            if answer is None and not self._cancelled:  # it ended as it was asked (idle):
                worker.close()  # once more, from a new one
                answer = await self._ask()
        finally:
            worker.busy = self._reading = False
        if answer is None:
            worker.close()  # killed, or died: the next plan starts another
            if not self._cancelled:
                raise OSError(errno.EPIPE, "the planning process ended before it answered")
            return None
        kind, value = answer
        if kind == "cancelled":
            return None
        if kind == "error":
            raise value
        return value  # type: ignore[no-any-return]

    async def _ask(self) -> tuple[str, Any] | None:
        try:
            connection = await asyncio.to_thread(self._worker.connection)
            if self._cancelled:
                return ("cancelled", None)  # before it was asked: the worker stays
            self._reading = True  # from now on a cancel kills the process
            await asyncio.to_thread(connection.send, self._request)  # (pickled in a thread)
            await _readable(connection)
            return await asyncio.to_thread(_answer, connection)
        except (OSError, EOFError):
            return None  # killed, or it ended (result() tells which)

    def cancel(self) -> None:
        """End the plan at once: the process is killed while it reads it."""
        self._cancelled = True
        if self._reading:
            self._worker.kill()


def _answer(connection: Connection) -> tuple[str, Any] | None:
    """The worker's answer, or None when it died first (in a thread; the pipe stays open)."""
    try:
        answer: tuple[str, Any] = connection.recv()
    except EOFError:
        return None
    return answer


def _serve(connection: Connection, idle_s: float) -> None:
    """The plan worker: read each plan asked for, send the result (or the error)."""
    gc.disable()  # the pipeline makes no reference cycles (see server.cli.offline); any
    parent = os.getppid()  # that a plan leaves are collected after it (the youngest objects)
    while True:
        try:
            if not connection.poll(idle_s):
                return  # idle: its memory back to the host (the next plan starts another)
            reader, path, core, interpreter = connection.recv()
        except (EOFError, OSError):
            return  # the server is gone
        answer = _read(reader, path, core, interpreter, lambda: os.getppid() != parent)
        if answer is None:
            return
        try:
            connection.send(answer)
        except OSError:
            return
        del answer
        gc.collect(0)  # what this plan left (a full collection would go over, and copy,
        # every object of the fork server's: tens of milliseconds)


class JobPlans:
    """The plans of one kernel's job files: the fit first, the time filled in when known.

    A file of at most :data:`FIT_FIRST_BYTES` is planned whole (fit and time together: a
    few tenths of a second at most) by the :class:`PlanWorker`; one of at most
    :data:`IN_THREAD_BYTES` in a thread until the worker runs (a few milliseconds: less than
    its start), and any while the worker reads another plan in a thread or a child of its
    own. For a larger one,
    :meth:`plan` reads the whole plan in one child and the fit alone in another (about a
    quarter of the work: it comes first, and on a busy host delays the time by no more than
    its share); it answers with
    the first fit (and the time, if it comes within :data:`TIMING_GRACE_S`) and fills in
    the plan's ``timing`` when it comes, calling ``on_timing(plan)``. The last
    :data:`KEPT_PLANS` plans are kept under their key (the file's size and time, the
    machine's state), so a job placed (the UI's preview) starts at once. :meth:`cancel`
    ends every plan being read (a stop, an abort).
    """

    def __init__(self, on_timing: Callable[[JobPlan], None]) -> None:
        self._on_timing = on_timing
        self._reading: set[PlanProcess[Any] | WorkerPlan[Any]] = set()
        self._worker = PlanWorker()
        self._stops: set[threading.Event] = set()  # the small plans read in a thread
        self._tasks: set[asyncio.Task[Any]] = set()
        self._kept: dict[str, tuple[object, JobPlan]] = {}

    async def plan(self, path: Path, core: CoreConfig, interpreter: Interpreter,
                   key: object, size_bytes: int) -> JobPlan:
        """The plan of ``path`` (``size_bytes`` long) from ``interpreter``'s state (a live
        copy, soft limits off), once its fit is known. Raises OSError, and
        :class:`~server.jobs.reading.Stopped` when cancelled first."""
        kept = self._kept.get(path.name)
        if kept is not None and kept[0] == key:
            return kept[1]
        worker = self._worker
        if size_bytes <= FIT_FIRST_BYTES and not worker.busy and (
                worker.running or size_bytes > IN_THREAD_BYTES):
            plan = await self._whole(worker.plan(read_plan, path, core, interpreter))
        elif size_bytes <= IN_THREAD_BYTES:
            plan = await self._in_thread(path, core, interpreter)
        elif size_bytes <= FIT_FIRST_BYTES:
            plan = await self._whole(PlanProcess(read_plan, path, core, interpreter))
        else:
            plan = await self._in_processes(path, core, interpreter)
        self._kept.pop(path.name, None)
        self._kept[path.name] = (key, plan)
        while len(self._kept) > KEPT_PLANS:
            del self._kept[next(iter(self._kept))]
        return plan

    async def _in_thread(self, path: Path, core: CoreConfig,
                         interpreter: Interpreter) -> JobPlan:
        stop = threading.Event()
        self._stops.add(stop)
        try:
            return await asyncio.to_thread(
                read_plan, path, core.model_copy(deep=True), interpreter, stop.is_set)
        finally:
            self._stops.discard(stop)

    async def _whole(self, process: PlanProcess[JobPlan] | WorkerPlan[JobPlan]) -> JobPlan:
        """The whole plan as ``process`` (the worker's, or a child's) reads it; Stopped when
        cancelled."""
        plan = await self._read(process)
        if plan is None:
            raise Stopped
        return plan

    async def _in_processes(self, path: Path, core: CoreConfig,
                            interpreter: Interpreter) -> JobPlan:
        """The whole plan in one child and the fit alone in another: the fit answers from
        whichever comes first."""
        whole = PlanProcess(read_plan, path, core, interpreter)
        planned = self._own(self._read(whole))
        fit = PlanProcess(read_fit, path, core, interpreter)
        fitted = self._own(self._read(fit))
        try:
            await asyncio.wait({planned, fitted}, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            self.cancel_all(whole, fit)
            raise
        if planned.done() or fitted.exception() is not None:
            self.cancel_all(fit)
            plan = await planned  # (raises what the reader raised)
        else:
            plan = fitted.result()
            if plan is not None:
                self._own(self._fill_in(path.name, plan, planned))
                await asyncio.wait({planned}, timeout=TIMING_GRACE_S)  # a small job's time
        if plan is None:
            whole.cancel()
            raise Stopped
        return plan

    async def _read(self, process: PlanProcess[JobPlan] | WorkerPlan[JobPlan]
                    ) -> JobPlan | None:
        self._reading.add(process)
        try:
            return await process.result()
        finally:
            self._reading.discard(process)

    def _own(self, work: Coroutine[Any, Any, T]) -> asyncio.Task[T]:
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    async def _fill_in(self, name: str, plan: JobPlan,
                       planned: asyncio.Task[JobPlan | None]) -> None:
        """The whole plan came: its time joins the plan answered with the fit."""
        try:
            whole = await planned
        except OSError as exc:
            log.warning("the time of %s is not known: %s", name, exc.strerror)
            whole = None
        if whole is None:  # stopped: the next plan reads it again
            self._kept = {name: kept for name, kept in self._kept.items() if kept[1] is not plan}
            return
        plan.timing = whole.timing
        self._on_timing(plan)

    @staticmethod
    def cancel_all(*processes: PlanProcess[Any] | None) -> None:
        for process in processes:
            if process is not None:
                process.cancel()

    def cancel(self) -> None:
        """End every plan being read, at once (a stop, an abort, the shutdown)."""
        for process in self._reading:
            process.cancel()
        for stop in self._stops:
            stop.set()

    async def close(self) -> None:
        """Cancel, wait for the owned tasks to end, end the plan worker."""
        self.cancel()
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=5.0)
        self._worker.close()

