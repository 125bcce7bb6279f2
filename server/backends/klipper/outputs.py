"""The Klipper backend's outputs on the motion's timeline, and the laser following the pieces.

:class:`OutputTiming` is the part of :class:`~.backend.KlipperBackend` (a base class of it) that
switches the board's pins. Outputs named in ``[backend.outputs]`` become
``queue_pwm_out``/``queue_digital_out`` at the MCU time of the motion time they are set for (a
line's actions: its block's start; otherwise the last sample) plus the lead, so they land on the
steps they belong to; so do the motors' enable pins (M17, M18). The laser's output follows the
pieces themselves (:meth:`OutputTiming.follow_power`: each piece carries its power law): on and
off exactly where a piece starts, and along the speed on a 1 ms grid of motion time. An output
that is on is sent again every half ``max_duration_s``: the firmware's watchdog turns it off
when motiond stops doing so.

Kept apart from the step schedule (:mod:`.schedule`) so that what a pin does, and when, reads
in one place: the schedule hands this part each piece it steps through
(:meth:`OutputTiming._follow_piece`), and this part times its messages with the schedule's map
from motion time to the MCU's clock. As a base class its methods are the backend's own (no
call goes through another object); its state is the backend's, created by
``KlipperBackend.__init__``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from server.backends.klipper.mcu import Mcu
from server.backends.klipper.movequeue import MoveQueue
from server.backends.klipper.pins import Axis, Output
from server.motion.backend import Piece


def level(value: float, top: int) -> int:
    """What the MCU is sent for ``value``: the PWM level out of ``top``, or on/off (top 0)."""
    if not top:
        return int(value > 0.5)
    return round(min(1.0, max(0.0, value)) * top)


class OutputTiming:
    """Outputs, motors and the followed power; see the module docstring."""

    # The backend's state this part reads and writes (set by KlipperBackend.__init__).
    axes: list[Axis]
    outputs: dict[str, Output]
    values: dict[str, float]
    motors_on: bool
    _enable_clock: int
    _motors_off_s: float
    pwm_log: list[tuple[float, str, float, int]] | None
    mcu: Mcu | None
    ready: bool
    _pieces: deque[Piece]
    _follow: Output | None
    _follow_period_s: float
    _follow_next_s: float
    _follow_on: bool
    _queue: MoveQueue
    _wake: Callable[[], None]

    if TYPE_CHECKING:
        def _when_s(self, time_s: float) -> float: ...  # the schedule's
        def _scheduled_clock(self, when_s: float) -> int: ...
        def _pump(self) -> None: ...

    def follow_power(self, name: str, period_s: float) -> bool:
        """The output ``name`` follows each piece's ``power`` (updated at most every
        ``period_s`` along an acceleration): the laser's PWM from the same piece as its steps."""
        out = self.outputs.get(name)
        if out is None:
            return False
        self._follow, self._follow_period_s = out, period_s
        return True

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

    def _follow_piece(self, piece: Piece, rel_s: float, first: bool) -> None:
        """The followed output's duty along ``piece`` up to ``rel_s`` into it. Turning on or
        off happens exactly where the piece starts; otherwise the duty is the piece's at
        every ``_follow_period_s`` of motion time (the laser's sample rate: S changing every
        segment of a fast raster costs at most one message a period)."""
        out, law, v0 = self._follow, piece.power, piece.start_mm_s
        assert out is not None
        start_s = piece.start_s
        top = self._level_top(out)
        duty = 0.0 if law is None else law.at(v0)  # where the piece starts
        if first:  # level(v, top) > 0 is v·top > 0.5 (a PWM level rounds to 0 up to 0.5)
            scale = top or 1
            on = out.value * scale > 0.5
            if not duty * scale > 0.5:
                if on:
                    self._set_followed(0.0, start_s, top)
            elif not on:
                self._set_followed(duty, start_s, top)
                self._follow_next_s = start_s + self._follow_period_s
        if law is None:
            return
        t, a, end_s = max(self._follow_next_s, start_s), piece.accel_mm_s2, start_s + rel_s
        if t <= end_s:  # the grid: the output is looked at only where its duty may change
            period_s, set_followed = self._follow_period_s, self._set_followed
            if a == 0.0 or law.per_mm_s == 0.0:  # one duty along the piece: the first look
                if duty != out.value:  # decides (the others would see the same)
                    set_followed(duty, t, top)
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
