"""Client helpers for the end-to-end streaming tests (test_real_senders, test_streaming_load).

* :class:`CharCountingClient`: Grbl's character-counting method over TCP on asyncio streams;
  it checks as it goes that the server never answers more lines than it was sent.
* :class:`MoveSpy`: records every move the planner of a running server accepts, in order.
* :func:`expected_run`: what a job must do, computed independently of any server (parser plus
  a fresh :class:`~server.gcode.interpreter.Interpreter`): its moves, end position and line errors.
* :class:`GrblStreamerRun` and :class:`PrintcoreRun`: drive the PyPI senders grbl-streamer and
  printrun's ``printcore`` (thread-based) from asyncio, counting what they sent and received.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from server.backends.sim import SimBackend
from server.config import CoreConfig
from server.errors import CommandError
from server.gcode.interpreter import Interpreter
from server.gcode.parser import parse_line
from server.machine.parts import interpreter_settings
from server.motion.moves import Move, Position

if TYPE_CHECKING:
    from server.machine.machine import Machine

BANNER = "Grbl 1.1h ['$' for help]"
RX_BUFFER_BYTES = 128


def fast_axes(travel_mm: float = 1000.0, rate_mm_s: float = 1000.0,
              accel_mm_s2: float = 20000.0) -> dict[str, dict[str, float]]:
    """An XYZ machine (80/80/400 steps/mm) with room and speed for any corpus job."""
    return {name: {"steps_per_mm": steps, "max_rate_mm_s": rate_mm_s, "accel_mm_s2": accel_mm_s2,
                   "min_mm": -travel_mm, "max_mm": travel_mm}
            for name, steps in (("x", 80.0), ("y", 80.0), ("z", 400.0))}


def scale_feeds(lines: Iterable[str], factor: float) -> list[str]:
    """The same job with every ``F`` word multiplied (same path, shorter in real time)."""
    word = re.compile(r"([Ff])\s*([0-9]*\.?[0-9]+)")
    return [word.sub(lambda m: f"{m.group(1)}{float(m.group(2)) * factor:g}", line)
            for line in lines]


# -- what a job must do --------------------------------------------------------------------------
@dataclass(slots=True)
class ExpectedRun:
    """A job run through parse_line + Interpreter, skipping refused lines as a server does."""

    targets: list[Position]
    end_mm: Position
    errors: dict[int, int]  # 0-based line index -> Grbl error code

    def end_steps(self, core: CoreConfig) -> list[int]:
        return [round(mm * axis.steps_per_mm)
                for mm, axis in zip(self.end_mm, core.axes.values(), strict=True)]


def expected_run(lines: Sequence[str], core: CoreConfig) -> ExpectedRun:
    """The moves, end position and refused lines of ``lines`` on the machine ``core``."""
    interpreter = Interpreter(interpreter_settings(core))
    interpreter.set_position(tuple(0.0 for _ in core.axis_names))
    targets: list[Position] = []
    errors: dict[int, int] = {}
    for index, text in enumerate(lines):
        if text.lstrip().startswith("$"):
            continue
        try:
            outputs = interpreter.execute(parse_line(text))
        except CommandError as exc:
            errors[index] = exc.code
            continue
        targets += [tuple(out.target_mm) for out in outputs if isinstance(out, Move)]
    return ExpectedRun(targets, tuple(interpreter.position), errors)


def backend_steps(machine: Machine) -> list[int]:
    """Steps the simulated backend has received per axis (absolute)."""
    backend = machine.backend
    assert isinstance(backend, SimBackend)
    return list(backend.steps)


class MoveSpy:
    """Records the target of every move the machine's planner accepts, in order."""

    def __init__(self, machine: Machine) -> None:
        self.targets: list[Position] = []
        planner = machine.planner
        original = planner.append

        def append(move: Move) -> bool:  # (the planner's answer: whether it is full now)
            self.targets.append(tuple(move.target_mm))
            return original(move)

        planner.append = append  # type: ignore[method-assign]


# -- character counting over TCP -----------------------------------------------------------------
@dataclass(slots=True)
class StreamResult:
    """Replies to streamed lines, in order, plus what else came back meanwhile."""

    replies: list[str] = field(default_factory=list)  # "ok" or "error:N", one per line sent
    messages: list[str] = field(default_factory=list)  # [MSG:...], [GC:...], pushes
    status: list[str] = field(default_factory=list)  # <...> reports
    extra_replies: int = 0  # replies with no unanswered line: must stay 0
    max_unacked_bytes: int = 0
    elapsed_s: float = 0.0


class CharCountingClient:
    """Streams lines keeping the bytes of unanswered lines at or under ``window``.

    Each ``ok`` or ``error:N`` frees the oldest unanswered line (Grbl's "character counting").
    """

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 window: int = RX_BUFFER_BYTES) -> None:
        self.reader, self.writer, self.window = reader, writer, window
        self.result = StreamResult()
        self.on_reply: Callable[[int, str], None] | None = None
        self._unacked: deque[int] = deque()
        self._unacked_bytes = 0
        self._room = asyncio.Event()
        self._closed = False

    @classmethod
    async def connect(cls, host: str, port: int, window: int = RX_BUFFER_BYTES,
                      timeout_s: float = 5.0) -> CharCountingClient:
        """Connect and wait for the banner."""
        reader, writer = await asyncio.open_connection(host, port)
        client = cls(reader, writer, window)
        while (await client._line(timeout_s)) != BANNER:
            pass
        return client

    async def _line(self, timeout_s: float | None = None) -> str:
        data = await asyncio.wait_for(self.reader.readline(), timeout_s)
        if not data:
            raise ConnectionError("the server closed the connection")
        return data.decode("utf-8", "replace").rstrip("\r\n")

    async def stream(self, lines: Sequence[str], *, idle_timeout_s: float = 30.0) -> StreamResult:
        """Send every line with character counting; return once each has its reply.

        Raises TimeoutError when no reply comes for ``idle_timeout_s``.
        """
        result = self.result
        expected = len(result.replies) + len(lines)
        receiver = asyncio.create_task(self._receive(expected, idle_timeout_s))
        started = time.perf_counter()
        try:
            for text in lines:
                data = text.encode() + b"\n"
                if len(data) > self.window:
                    raise ValueError(f"line longer than the window: {text!r}")
                while self._unacked_bytes + len(data) > self.window:
                    if receiver.done():
                        receiver.result()
                        raise ConnectionError("receiver ended early")
                    self._room.clear()
                    room = asyncio.create_task(self._room.wait())
                    await asyncio.wait({receiver, room}, return_when=asyncio.FIRST_COMPLETED)
                    room.cancel()
                self._unacked.append(len(data))
                self._unacked_bytes += len(data)
                result.max_unacked_bytes = max(result.max_unacked_bytes, self._unacked_bytes)
                self.writer.write(data)
                if self.writer.transport.get_write_buffer_size() > 65536:
                    await self.writer.drain()
            await receiver
        finally:
            if not receiver.done():
                receiver.cancel()
        result.elapsed_s = time.perf_counter() - started
        return result

    async def _receive(self, expected: int, idle_timeout_s: float) -> None:
        result = self.result
        while len(result.replies) < expected:
            line = await self._line(idle_timeout_s)
            if line == "ok" or line.startswith("error:"):
                if not self._unacked:
                    result.extra_replies += 1
                    continue
                self._unacked_bytes -= self._unacked.popleft()
                result.replies.append(line)
                if self.on_reply is not None:
                    self.on_reply(len(result.replies) - 1, line)
                self._room.set()
            elif line.startswith("<"):
                result.status.append(line)
            elif line:
                result.messages.append(line)

    async def command(self, text: str, timeout_s: float = 5.0) -> list[str]:
        """Send-response: one line, every line up to and including its ok/error."""
        assert not self._unacked, "command() while streamed lines are unanswered"
        self.writer.write(text.encode() + b"\n")
        got: list[str] = []
        while True:
            line = await self._line(timeout_s)
            if line.startswith("<") or not line:
                continue
            got.append(line)
            if line == "ok" or line.startswith("error:"):
                return got

    async def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.writer.close()
            with contextlib.suppress(OSError, TimeoutError):
                await asyncio.wait_for(self.writer.wait_closed(), 2.0)


class StatusPoller:
    """A second client sending ``?`` at a fixed rate; records each report's latency."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.latencies_s: list[float] = []
        self.reports: list[str] = []
        self.sent = 0
        self.others: list[str] = []

    @classmethod
    async def connect(cls, host: str, port: int) -> StatusPoller:
        reader, writer = await asyncio.open_connection(host, port)
        poller = cls(reader, writer)
        while (await asyncio.wait_for(reader.readline(), 5.0)).strip().decode() != BANNER:
            pass
        return poller

    async def run(self, rate_hz: float, stop: asyncio.Event, timeout_s: float = 2.0) -> None:
        """Poll until ``stop`` is set; a report that does not come within ``timeout_s`` fails."""
        period_s = 1.0 / rate_hz
        loop = asyncio.get_running_loop()
        next_s = loop.time()
        while not stop.is_set():
            sent_s = loop.time()
            self.writer.write(b"?")
            self.sent += 1
            while True:
                line = (await asyncio.wait_for(self.reader.readline(), timeout_s)).decode()
                if line.startswith("<"):
                    break
                self.others.append(line.rstrip())
            self.latencies_s.append(loop.time() - sent_s)
            self.reports.append(line.rstrip())
            next_s += period_s
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), max(0.0, next_s - loop.time()))

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError, TimeoutError):
            await asyncio.wait_for(self.writer.wait_closed(), 2.0)


# -- threaded PyPI senders ------------------------------------------------------------------------
async def wait_for(condition: Callable[[], bool], timeout_s: float, what: str,
                   period_s: float = 0.02) -> None:
    """Poll ``condition`` from asyncio until it holds; AssertionError naming ``what`` if not."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        await asyncio.sleep(period_s)


class GrblStreamerRun:
    """One grbl-streamer ``GrblStreamer`` on a serial device, with its events counted.

    grbl-streamer writes ``$$``/``$#``/``$G`` outside its character counting and answers the
    first ``ok`` it gets with its oldest streamed line, so the job starts only once every boot
    query has been answered (as its own GUI users do by waiting for the settings).

    grbl-streamer fills the window from two threads without a lock: the caller of ``job_run``
    and its reader thread (on each ``ok``). At 115200 baud the first ``ok`` comes long after
    the first fill; over a pty motiond answers within microseconds and the two threads then
    send lines twice, skip or swap them (seen here: ``M03S80`` written after two moves). The
    two entry points are serialised with one lock, which is what the library's own callers
    would need; ``wire`` records what really went down the device, in order.
    """

    def __init__(self) -> None:
        from grbl_streamer import GrblStreamer

        self.lock = threading.Lock()
        self.writes: list[str] = []  # lines written that expect a reply (job and queries)
        self.oks = 0
        self.sent: list[str] = []  # job lines, as rewritten and sent
        self.processed = 0  # job lines the sender saw acknowledged
        self.errors: list[tuple[Any, ...]] = []
        self.alarms: list[str] = []
        self.states: list[tuple[str, tuple[float, ...]]] = []
        self.boots = 0
        self.wire: list[str] = []  # every line written to the device once connected
        self._job_start = 0
        self.streamer = GrblStreamer(self._event, name="motiond-test")
        streaming = threading.RLock()
        original_ok, original_stream = self.streamer._handle_ok, self.streamer._stream

        def handle_ok() -> None:
            with self.lock:
                self.oks += 1
            with streaming:
                original_ok()

        def stream() -> None:
            with streaming:
                original_stream()

        self.streamer._handle_ok = handle_ok  # type: ignore[method-assign]
        self.streamer._stream = stream  # type: ignore[method-assign]

    def _event(self, name: str, *args: Any) -> None:
        with self.lock:
            if name == "on_write" and args[0].endswith("\n"):
                self.writes.append(args[0])
            elif name == "on_line_sent":
                self.sent.append(args[1])
            elif name == "on_processed_command":
                self.processed += 1
            elif name == "on_error":
                self.errors.append(args)
            elif name == "on_alarm":
                self.alarms.append(args[0])
            elif name == "on_stateupdate":
                self.states.append((args[0], tuple(args[1])))
            elif name == "on_boot":
                self.boots += 1

    def settled(self) -> bool:
        """Booted, boot queries sent by the poller and every written line answered."""
        streamer = self.streamer
        with self.lock:
            return (streamer.connected and not streamer.hash_state_requested
                    and not streamer.gcode_parser_state_requested
                    and len(self.writes) >= 3 and self.oks == len(self.writes))

    async def connect(self, device: str, timeout_s: float = 10.0) -> None:
        await asyncio.to_thread(self.streamer.cnect, device, 115200)
        interface = self.streamer._iface
        original_write = interface.write

        def write(data: str) -> int | None:
            if data.endswith("\n"):
                with self.lock:
                    self.wire.append(data[:-1])
            return original_write(data)

        interface.write = write  # type: ignore[method-assign]
        await wait_for(lambda: self.streamer.connected, timeout_s, "the Grbl banner")
        self.streamer.poll_start()
        await wait_for(self.settled, timeout_s, "answers to $$, $# and $G")

    def job_wire(self) -> list[str]:
        """The job's lines as written to the device (the poller's ``$`` queries left out)."""
        with self.lock:
            return [line for line in self.wire[self._job_start:] if not line.startswith("$")]

    async def run_job(self, lines: Sequence[str], timeout_s: float) -> None:
        streamer = self.streamer
        with self.lock:
            self._job_start = len(self.wire)
        await asyncio.to_thread(streamer.write, list(lines))
        await asyncio.to_thread(streamer.job_run)
        await wait_for(lambda: streamer.job_finished and streamer.streaming_complete, timeout_s,
                       "grbl-streamer to finish the job", period_s=0.05)

    async def close(self) -> None:
        streamer = self.streamer
        if streamer.connected:
            await asyncio.to_thread(streamer.disconnect)
            return
        if streamer._iface is not None:  # never booted: disconnect() would do nothing
            await asyncio.to_thread(streamer._iface.stop)
            streamer._iface = None
        if streamer._thread_read_iface is not None:
            streamer._iface_read_do = False
            streamer._queue.put("stop")
            await asyncio.to_thread(streamer._thread_read_iface.join)


class PrintcoreRun:
    """One printrun ``printcore`` (TCP ``host:port`` or a serial device), its traffic counted."""

    def __init__(self) -> None:
        from printrun.printcore import printcore

        self.lock = threading.Lock()
        self.sent: list[str] = []
        self.received: list[str] = []
        self.oks = 0
        self.core = printcore()
        self.core.sendcb = self._sent
        self.core.recvcb = self._received
        self.core.errorcb = self._error
        self.host_errors: list[str] = []

    def _sent(self, command: str, gline: Any) -> None:
        with self.lock:
            self.sent.append(command)

    def _received(self, line: str) -> None:
        with self.lock:
            self.received.append(line.rstrip())
            if line.startswith("ok"):
                self.oks += 1

    def _error(self, error: str) -> None:
        with self.lock:
            self.host_errors.append(error)

    def refusals(self) -> list[str]:
        """Lines in which the server refused something (Marlin wording) or asked for a resend."""
        with self.lock:
            return [line for line in self.received
                    if line.startswith(("Error", "error", "echo:", "Resend", "rs ", "!!"))]

    async def connect(self, port: str, timeout_s: float = 10.0) -> None:
        await asyncio.to_thread(self.core.connect, port, 115200)
        await wait_for(lambda: self.core.online, timeout_s, "printcore to come online")
        await wait_for(lambda: self.oks >= 1, timeout_s, "the answer to M105")

    async def run_job(self, lines: Sequence[str], timeout_s: float) -> None:
        from printrun import gcoder

        gcode = await asyncio.to_thread(gcoder.LightGCode, list(lines))
        assert self.core.startprint(gcode), "printcore refused to start the print"
        await wait_for(lambda: not self.core.printing, timeout_s, "printcore to finish the print",
                       period_s=0.05)
        await wait_for(lambda: self.oks == len(self.sent), 10.0, "an ok for every sent line")

    async def close(self) -> None:
        await asyncio.to_thread(self.core.disconnect)


def job_lines_from(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()
