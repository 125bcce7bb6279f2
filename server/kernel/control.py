"""Realtime commands, soft reset and halt: one implementation for every entry point.

A line session (TCP, pty, ``/ws``), the JSON API and a job's controls all call
:class:`MachineControl`, so ``!``, ``~``, Ctrl-X and M112 mean exactly the same wherever they
come from: a hold pauses a running job (and the motion), a resume continues it, a reset stops
motion and ends the job, an emergency stop alarms the machine with the tools off.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from server.protocol.events import Realtime

if TYPE_CHECKING:
    from server.jobs.jobs import Jobs
    from server.machine.machine import Machine

_HOLDS = frozenset({Realtime.HOLD, Realtime.DOOR})
_TOGGLES = (Realtime.SPINDLE_STOP, Realtime.FLOOD, Realtime.MIST)
_ONCE = frozenset({Realtime.HOLD, Realtime.DOOR, Realtime.RESUME, Realtime.JOG_CANCEL,
                   Realtime.STATUS, Realtime.RESET})
_M112 = re.compile(r"^\s*(?:N\d+\s*)?M\s*0*112(?:\D|$)", re.I)
_M410 = re.compile(r"^\s*(?:N\d+\s*)?M\s*0*410(?:[^\d.]|$)", re.I)
# bytes in which a line may be one of those two (found anywhere; a line with other whitespace
# than ASCII's has bytes above 0x7F, one with control characters is refused)
MAY_STOP_AT_ONCE = re.compile(rb"[Mm]\s*0*(?:112|410)")


def halts_at_once(text: str) -> bool:
    """Whether a line is an M112 that acts the moment it arrives, ahead of queued lines."""
    return _M112.match(text) is not None


def quickstops_at_once(text: str) -> bool:
    """Whether a line is an M410 quickstop, acted on the moment it arrives (as Marlin's
    emergency parser does): the motion queued ahead of it is dropped."""
    return _M410.match(text) is not None


class MachineControl:
    """Hold, resume, reset, jog cancel, overrides and emergency stop, acted on at once."""

    def __init__(self, machine: Machine, jobs: Jobs) -> None:
        self.machine = machine
        self.jobs = jobs

    def realtime(self, command: Realtime) -> None:
        """A realtime byte other than ``?`` (status is the asking connection's to answer)."""
        if command is Realtime.HOLD:
            self.hold()
        elif command is Realtime.RESUME:
            self.resume()
        elif command is Realtime.RESET:
            self.reset()
        else:
            self.machine.realtime(command)

    def realtime_batch(self, commands: Sequence[Realtime]) -> None:
        """Realtime bytes (not ``?``, not Ctrl-X) that arrived together, folded as Grbl's
        realtime flags fold them, so a flood costs a few actions whatever its size: a hold
        (``!``, safety door) acts once, at once; ``~`` resumes after it only when it came after
        the last hold; a jog cancel acts once; the override steps give one change (each step
        clamped as it would have been alone); a toggle acts if it came an odd number of times.
        A command that repeats the state (a second ``!`` while held, an override at its
        limit) changes nothing and costs nearly nothing."""
        holds = [index for index, command in enumerate(commands) if command in _HOLDS]
        if holds:
            self.realtime(commands[holds[0]])
        if Realtime.JOG_CANCEL in commands:
            self.jog_cancel()
        resumes = [index for index, command in enumerate(commands) if command is Realtime.RESUME]
        if resumes and (not holds or resumes[-1] > holds[-1]):
            self.resume()
        self.machine.step_overrides([c for c in commands if c not in _ONCE
                                     and c not in _TOGGLES])
        for toggle in _TOGGLES:
            if commands.count(toggle) % 2:
                self.realtime(toggle)

    def hold(self) -> None:
        """``!``: decelerate to a stop on the path; a running job is paused."""
        if self.jobs.is_playing():
            self.jobs.suspend()
        else:
            self.machine.feed_hold()

    def resume(self) -> None:
        """``~``: continue exactly where the hold stopped; a paused job plays on."""
        if self.jobs.is_paused():
            self.jobs.resume()
        else:
            self.machine.cycle_start()

    def reset(self) -> None:
        """Ctrl-X: stop at once and flush (ALARM:3 if it was moving); a job ends."""
        self.machine.soft_reset()
        if self.jobs.active:
            self.jobs.abort()

    def jog_cancel(self) -> None:
        self.machine.cancel_jog()

    def cancel_job(self) -> None:
        """Abort the running or paused job, as Smoothie's ``abort`` (nothing without one)."""
        if self.jobs.active:
            self.jobs.abort()

    def set_feed_override(self, percent: int) -> None:
        """The feed override, in percent (clamped to Grbl's 10-200), as 0x90-0x94 set it."""
        self.machine.set_overrides(feed=percent)

    def quickstop(self) -> None:
        """M410: stop at once, flush the queue, tools off, no alarm; a running job ends;
        a stop (what anyone queued before it is dropped)."""
        if self.jobs.active:
            self.jobs.abort("quickstop (M410)")
        else:
            self.machine.quickstop()
            self.machine.status.stop("quickstop (M410)")

    def emergency_stop(self) -> None:
        """M112: ALARM:40, motion stopped and tools off until ``$X`` or M999."""
        self.machine.emergency_stop()
