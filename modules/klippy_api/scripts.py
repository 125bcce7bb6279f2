"""One connection's ``gcode/script`` requests: queued, run one after another, each answered
when it ends.

Each line runs through ``ModuleContext.run_gcode``, the ordered path of every sender, so a
script waiting for planner room never delays a query, a pause or an emergency stop. A script
holding only ``PAUSE``/``RESUME``/``CANCEL_PRINT``/``M112`` acts on arrival, as the realtime
bytes of a Grbl sender do, and an ``M112`` anywhere in a script acts on arrival too.

Bounds: at most :data:`PENDING_SCRIPTS` wait per connection, and all connections' waiting
scripts share the hub's byte budget; beyond either, a script is refused at once (error 45).
A script of up to :data:`SHORT_SCRIPT_CHARS` is translated on arrival; a longer one waits as
text and, when its turn comes, is translated piece by piece (once to check it, since nothing
of a malformed script runs, then again as it runs) with the loop's turn between pieces and
between lines: a script of 1 MiB never holds the loop. When the connection goes, its waiting
scripts are dropped and their bytes given back (:meth:`Scripts.close`).
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

from modules.klippy_api import gcode, outputs, wire
from modules.klippy_api.gcode import (
    Control,
    FeedOverride,
    GcodeOffset,
    Line,
    Message,
    SetPin,
    StartJob,
    Step,
)
from modules.klippy_api.hub import Hub
from server.errors import CommandError, Error
from server.kernel.module import ModuleContext

PENDING_SCRIPTS = 32
SHORT_SCRIPT_CHARS = 1024  # the front-ends' scripts (a jog, PAUSE, a macro call)
SCAN_PIECE_CHARS = 65536  # a long script is searched for M112 this much at a time (~0.6 ms)
IMMEDIATE = frozenset({"pause", "resume", "cancel", "estop"})


@dataclass(frozen=True, slots=True)
class Script:
    """A queued script: its steps when translated on arrival, else its text; ``size_bytes``
    is what it holds of the hub's byte budget; ``ticket`` its stop generation (a stop before
    it ran, or while it runs, ends it whatever it waits for: a deferred jog too)."""

    request_id: Any
    steps: list[Step] | None
    text: str
    size_bytes: int
    ticket: int  # the stop generation it was sent in: after a stop, none of it runs


class Scripts:
    """A connection's scripts (:meth:`submit`, :meth:`run` in a task, :meth:`close`)."""

    def __init__(self, hub: Hub, send: Callable[[dict[str, Any]], None]) -> None:
        self.hub, self.send = hub, send
        self._queue: asyncio.Queue[Script] = asyncio.Queue(PENDING_SCRIPTS)
        self._held_bytes = 0

    async def submit(self, request_id: Any, script: str) -> dict[str, Any] | None:
        """Act on the script now (an empty answer), or queue it (None: answered when it has
        run); raises :class:`CommandError` when it is malformed or refused. Only a long
        script's search for ``M112`` awaits (the loop budget, between pieces)."""
        ticket = self.hub.ctx.ticket()
        if len(script) > SHORT_SCRIPT_CHARS:
            if await self._stops_at_once(script):
                control(self.hub.ctx, "estop")  # on arrival, as from every other source
            self.queue(Script(request_id, None, script, sys.getsizeof(script), ticket))
            return None
        if gcode.stops_at_once(script):
            control(self.hub.ctx, "estop")
        steps = gcode.translate(script, self.hub.jog_feed_mm_min)
        if steps and all(isinstance(s, Control) and s.action in IMMEDIATE for s in steps):
            for step in steps:
                control(self.hub.ctx, step.action)  # type: ignore[union-attr]
            return {}
        self.queue(Script(request_id, steps, "", sys.getsizeof(script), ticket))
        return None

    async def _stops_at_once(self, script: str) -> bool:
        budget = self.hub.budget
        for piece in gcode.pieces(script, SCAN_PIECE_CHARS):
            await budget.turn()
            if gcode.stops_at_once(piece):
                return True
        return False

    def queue(self, script: Script) -> None:
        if self._queue.full():
            raise CommandError(Error.BUSY, "too many G-code scripts waiting")
        if not self.hub.script_bytes.take(script.size_bytes):
            limit_kib = self.hub.script_bytes.limit_bytes >> 10
            raise CommandError(Error.BUSY, f"G-code scripts waiting hold {limit_kib} KiB "
                                           "already; send it again later")
        self._held_bytes += script.size_bytes
        self._queue.put_nowait(script)

    def close(self) -> None:
        """Drop the waiting scripts and give back their bytes (the connection went)."""
        while not self._queue.empty():
            self._queue.get_nowait()
        self.hub.script_bytes.give(self._held_bytes)
        self._held_bytes = 0

    async def run(self) -> None:
        """Run queued scripts in order until cancelled; each is answered when it ends."""
        while True:
            script = await self._queue.get()
            try:
                await self._run(script)
            except CommandError as exc:
                self.hub.output(f"!! {error_text(exc)}")
                self.send(wire.error(script.request_id, error_text(exc)))
            else:
                self.send(wire.result(script.request_id, {}))
            finally:
                self._held_bytes -= script.size_bytes
                self.hub.script_bytes.give(script.size_bytes)

    async def _run(self, script: Script) -> None:
        if script.steps is not None:
            await self._run_steps(script.steps, script.ticket)
            return
        budget, feed_mm_min = self.hub.budget, self.hub.jog_feed_mm_min
        for piece in gcode.pieces(script.text):  # all of it checked before any of it runs
            await budget.turn()
            gcode.translate_piece(piece, feed_mm_min)
        for piece in gcode.pieces(script.text):
            await budget.turn()
            steps = gcode.translate_piece(piece, feed_mm_min)
            await self._run_steps(steps, script.ticket)

    async def _run_steps(self, steps: list[Step], ticket: int) -> None:
        budget = self.hub.budget
        for step in steps:
            await budget.turn()
            await self._step(step, ticket)

    async def _step(self, step: Step, ticket: int) -> None:
        ctx = self.hub.ctx
        if not ctx.still_valid(ticket):
            raise CommandError(Error.BUSY, "a stop came after this script was sent: not run")
        if isinstance(step, Line):
            gcode.check_line_during_job(step.text, self.hub.job_state)
            try:
                messages = await ctx.run_gcode(step.text, ticket)
            except CommandError as exc:
                raise gcode.klipper_error(step.text, exc) from exc
            for message in messages:
                self.hub.output(response_text(message))
        elif isinstance(step, StartJob):
            await ctx.start_job(step.name, ticket)
        elif isinstance(step, SetPin):
            line = outputs.set_pin_line(ctx.status(), step.pin, step.value)
            await self._step(Line(line), ticket)
        elif isinstance(step, FeedOverride):
            ctx.control.set_feed_override(step.percent)
        elif isinstance(step, Message):
            self.hub.set_message(step.text)
        elif isinstance(step, GcodeOffset):
            await _gcode_offset(ctx, step, ticket, self.hub.output)
        elif step.action == "help":
            self.hub.output("\n".join(["// Available commands:",
                                       *(f"// {k}: {v}" for k, v in gcode.HELP.items())]))
        elif step.action == "velocity_limit":
            toolhead = self.hub.objects()["toolhead"]
            self.hub.output(gcode.velocity_report(toolhead["max_velocity"],
                                                  toolhead["max_accel"]))
        elif step.action == "restart":  # a reset board, as Klipper's restarts leave it
            ctx.control.reset()
            await ctx.run_gcode("$X")
            await ctx.run_gcode("M84")  # motors off, homing lost: as after Klipper's restart
            await ctx.moves.wait_idle()  # (M84 is ordered with motion: done before the answer)
            self.hub.restart()
        else:
            control(ctx, step.action)


async def _gcode_offset(ctx: ModuleContext, step: GcodeOffset, ticket: int,
                        output: Callable[[str], None]) -> None:
    """``SET_GCODE_OFFSET`` as motiond's babystep, ``M290``: the work offset
    (``homing_origin``) changes by the difference and, with ``MOVE=1``, the head moves by it
    (at the rapid rate; ``MOVE_SPEED`` is not used), in order with the queued moves.

    During a running job the line runs as part of it, before its next line: every later
    move of the job is shifted, and the answer comes once it has run (a stop first: error
    45, never run). A paused job holds its next line until Resume, so the answer comes at
    once and the console says when the change ran, or why not. Otherwise the line runs once
    the queued moves ran, answered after the move. An absolute ``Z=`` is taken against the
    offset when the command arrives."""
    status = ctx.status()
    line = _offset_line(status, ctx.core.axis_names, step)
    if line is None:
        return
    answer = ctx.run_in_job(line, ticket)
    if answer is not None and (status.get("job") or {}).get("state") == "paused":
        output("// SET_GCODE_OFFSET: the job is paused; the offset applies when it resumes")
        answer.add_done_callback(partial(_report_later, output))
        return
    if answer is not None:
        if await answer is not None:
            return
        if (ctx.status().get("job") or {}).get("state") != "done":  # failed first (an abort
            # is a stop: the ticket would refuse it too, with a vaguer message)
            raise CommandError(Error.BUSY, "SET_GCODE_OFFSET not applied: the job ended first")
    await ctx.moves.wait_idle()
    await ctx.run_gcode(line, ticket)
    await ctx.moves.wait_idle()


def _offset_line(status: dict[str, Any], names: Sequence[str], step: GcodeOffset) -> str | None:
    """The ``M290`` line that makes the offsets those ``step`` asks for (None: no axis)."""
    wco = status["wco"]
    deltas: dict[str, float] = {}
    for axis in sorted(set(step.absolute) | set(step.adjust)):
        if axis not in names:
            raise CommandError(Error.UNSUPPORTED, f"SET_GCODE_OFFSET: no axis {axis}")
        index = names.index(axis)
        target = step.absolute.get(axis, wco[index]) + step.adjust.get(axis, 0.0)
        deltas[axis] = target - wco[index]
    if not deltas:
        return None
    scale = 25.4 if status.get("modal", {}).get("units") == "in" else 1.0
    words = " ".join(f"{axis}{delta / scale:.6f}" for axis, delta in deltas.items())
    return f"M290 {words}" + ("" if step.move else " P0")


def _report_later(output: Callable[[str], None],
                  answer: asyncio.Future[list[str] | None]) -> None:
    """The console learns what became of an offset change queued in a pause."""
    if answer.cancelled():
        return
    failure = answer.exception()
    if isinstance(failure, CommandError):
        output(f"!! SET_GCODE_OFFSET not applied: {error_text(failure)}")
    elif answer.result() is None:
        output("!! SET_GCODE_OFFSET not applied: the job ended before it resumed")
    else:
        output("// SET_GCODE_OFFSET applied")


def control(ctx: ModuleContext, action: str) -> None:
    """Hold, resume, cancel the job, or stop at once, as every other source does."""
    controls = ctx.control
    if action == "pause":
        controls.hold()
    elif action == "resume":
        controls.resume()
    elif action == "cancel":
        controls.cancel_job()
    elif action == "estop":
        controls.emergency_stop()


def response_text(message: str) -> str:
    """A motiond reply line as Klipper's console shows it: ``[MSG:x]`` is ``// x``; alarms
    and errors are ``!! ...``; M114's ``C: X:..`` loses the ``C:`` (Klipper's M114 starts at
    ``X:``, and the front-ends hide ``C:`` lines as temperature reports)."""
    if message.startswith("C: X:"):
        return message[3:]
    if message.startswith("[MSG:") and message.endswith("]"):
        return f"// {message[5:-1]}"
    if message.startswith(("ALARM:", "error:")):
        return f"!! {message}"
    return message


def error_text(exc: CommandError) -> str:
    return f"error:{int(exc.code)} {exc.message}".strip()
