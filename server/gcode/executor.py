"""The general path of the interpreter: one classified line -> outputs, on copies of the state.

:class:`LineExecutor` applies a line's words in Grbl's order of execution (feed mode, F, S, T,
M6, M3-M5, coolant, dwell, plane, units, tool length, coordinate system, distance modes,
non-modal commands, motion, program flow) to *copies* of the modal state and offsets. The
interpreter commits the copies only when :meth:`LineExecutor.run` returns; a refused line
raises :class:`~server.errors.CommandError` and leaves nothing behind.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from server.errors import CommandError, Error, SoftLimitError
from server.gcode import arcs
from server.gcode.codes import CodeCall
from server.gcode.modal import (
    AXIS_COMMANDS,
    G0,
    G1,
    G2,
    G3,
    G80,
    MM_PER_INCH,
    WCS_CODES,
    Geometry,
    ModalState,
    Offsets,
    Words,
)
from server.gcode.nonmodal import NonModal
from server.motion.moves import (
    Action,
    ActionName,
    Move,
    MoveKind,
    Output,
    Position,
    Sync,
    SyncKind,
    ToolMode,
)

if TYPE_CHECKING:
    from server.gcode.codes import CodeTable

PLANE_AXES = {17: ("X", "Y"), 18: ("Z", "X"), 19: ("Y", "Z")}
PLANE_OFFSETS = {17: ("I", "J"), 18: ("K", "I"), 19: ("J", "K")}
ALWAYS_USED = frozenset("FST")
# Grbl counts a dwell in 50 ms steps in a uint16, so it cannot dwell past 3276.75 s; an hour
# refuses no dwell Grbl can perform and catches P written in milliseconds (Marlin's unit).
MAX_DWELL_S = 3600.0


class LineExecutor(NonModal):
    """Executes one line on copies of the state; read ``modal``, ``offsets``, ``position``
    and ``wco`` after :meth:`run` to commit them."""

    def __init__(
        self,
        geometry: Geometry,
        modal: ModalState,
        offsets: Offsets,
        position: Position,
        words: Words,
        line_number: int | None,
        codes: CodeTable | None = None,
    ) -> None:
        self.geo = geometry
        self.codes = codes
        self.words = words
        self.start = modal
        self.modal = modal.copy()
        self.offsets = offsets.copy()
        self.position = position
        self.wco = offsets.wco(modal.wcs, geometry.z_axis)
        self.line_number = line_number
        self.axes_used = False
        self.values_used: set[str] = set()
        self.first: list[Output] = []
        self.before: list[Output] = []
        self.moves: list[Output] = []
        self.after: list[Output] = []

    def run(self) -> list[Output]:
        """Apply the line; raise CommandError (state copies then discarded) if it is invalid."""
        self._modes()
        self._feed()
        self._tools()
        self._module_codes()
        self._m_commands()
        self._dwell()
        self._tool_length()
        self.wco = self.offsets.wco(self.modal.wcs, self.geo.z_axis)
        self.non_modal()
        self.babystep()
        self.wco = self.offsets.wco(self.modal.wcs, self.geo.z_axis)
        self._motion()
        self._check_unused()
        self._program_flow()
        return self.first + self.before + self.moves + self.after

    # -- modes and tools ---------------------------------------------------------------------
    def _modes(self) -> None:
        g, m = self.words.g, self.modal
        if (code := g("feed_mode")) is not None:
            m.inverse_time = code == 930
        if (code := g("units")) is not None:
            m.inches = code == 200
        if (code := g("plane")) is not None:
            m.plane = code // 10
        if (code := g("distance")) is not None:
            m.incremental = code == 910
        if (code := g("arc_distance")) is not None:
            m.arc_absolute = code == 901
        if (code := g("wcs")) is not None:
            m.wcs = WCS_CODES.index(code)
        if (code := g("motion")) is not None:
            m.motion = code

    def _feed(self) -> None:
        m, f = self.modal, self.words.values.get("F")
        if f is not None:
            m.feed = f if m.inverse_time else f * (MM_PER_INCH if m.inches else 1.0)
        elif m.inverse_time or self.start.inverse_time:
            m.feed = 0.0  # G93 needs F on each line; G93 -> G94 leaves the feed undefined

    def _tools(self) -> None:
        m, values, g = self.modal, self.words.values, self.words.g
        if "S" in values and not self._module_uses("S"):  # (M221 S50 is no spindle speed)
            m.s = values["S"]
        if "T" in values:
            m.tool = int(values["T"])
        if g("m_tool_change") is not None:
            self.before.append(Action(ActionName.TOOL_CHANGE, {"tool": m.tool}, stops_motion=True))
        if (code := g("m_spindle")) is not None:
            m.tool_mode = ToolMode(code)
        if code is not None or m.s != self.start.s:
            self.before.append(Action(ActionName.SPINDLE, {"mode": m.tool_mode, "s": m.s}))
            self._spin_up()
        if (code := g("m_coolant")) is not None:
            m.mist = code == 7 or (m.mist and code == 8)
            m.flood = code == 8 or (m.flood and code == 7)
            self.before.append(Action(ActionName.COOLANT, {"mist": m.mist, "flood": m.flood}))

    def _spin_up(self) -> None:
        """A spindle starting from off makes motion wait ``spin_up_delay_s`` (grblHAL's $340)."""
        delay_s, m = self.geo.settings.spin_up_delay_s, self.modal
        was_on = self.start.tool_mode is not ToolMode.OFF and self.start.s > 0
        if delay_s > 0 and not was_on and m.tool_mode is not ToolMode.OFF and m.s > 0:
            self.before.append(Action(ActionName.DWELL, {"seconds": delay_s, "reason": "spin-up"},
                                      lead_s=delay_s, stops_motion=True))

    def _module_uses(self, letter: str) -> bool:
        """Whether an M-code of a module on the line reads ``letter`` (its value is then that
        code's, as Marlin's M221 S or M106 S are: not the spindle's speed)."""
        codes, values = self.codes, self.words.values
        return codes is not None and any(
            letter in codes.lookup(code, values).uses for code in self.words.module_codes)

    def _module_codes(self) -> None:
        """M-codes that modules own, after coolant (see :mod:`server.gcode.codes`)."""
        if not self.words.module_codes:
            return
        assert self.codes is not None
        values = self.words.values
        for code in self.words.module_codes:
            spec = self.codes.lookup(code, values)
            self.values_used |= spec.uses
            for output in spec.factory(CodeCall(code, values, self.line_number)):
                (self.after if isinstance(output, Sync) else self.before).append(output)

    def _m_commands(self) -> None:
        g = self.words.g
        if (code := g("m_motors")) is not None:
            if code == 17:
                self.before.append(Action(ActionName.MOTORS, {"enabled": True}))
            else:
                self.after.append(Action(ActionName.MOTORS, {"enabled": False}, stops_motion=True))
        code = g("m_sync")
        if code == 112:
            self.first.append(Sync(SyncKind.HALT))
        elif code == 999:
            self.first.append(Sync(SyncKind.CLEAR_HALT))
        elif code == 114:
            self.after.append(Sync(SyncKind.REPORT_POSITION))
        elif code == 400:
            self.after.append(Sync(SyncKind.WAIT))
        elif code == 410:
            self.first.append(Sync(SyncKind.QUICKSTOP))

    def _dwell(self) -> None:
        if self.words.g("non_modal") != 40:
            return
        seconds = self.words.values.get("P")
        if seconds is None:
            raise CommandError(Error.VALUE_WORD_MISSING, "G4 needs a P word (seconds)")
        if seconds > MAX_DWELL_S:
            raise CommandError(Error.BAD_NUMBER_FORMAT, f"G4 P{seconds:g}: over {MAX_DWELL_S:g} s")
        self.values_used.add("P")
        dwell = Action(ActionName.DWELL, {"seconds": seconds}, lead_s=seconds, stops_motion=True)
        self.before.append(dwell)

    def _tool_length(self) -> None:
        code = self.words.g("tool_length")
        if code == 490:
            self.offsets.tlo_mm = 0.0
        elif code == 431:
            z, axes = self.geo.z_axis, self.words.axes
            if z is None or set(axes) != {z}:
                raise CommandError(Error.TLO_AXIS, "G43.1 takes exactly one Z word")
            self.offsets.tlo_mm = axes[z] * (MM_PER_INCH if self.modal.inches else 1.0)
            self.axes_used = True

    # -- motion ------------------------------------------------------------------------------
    def _motion(self) -> None:
        code, words = self.words.g("motion"), self.words
        explicit = code is not None and code != G80
        other_command = any(
            c in AXIS_COMMANDS for k, c in words.groups.items() if k in ("non_modal", "tool_length")
        )
        other_command = other_command or words.g("m_offset") is not None
        if not explicit and (not words.axes or other_command):
            return
        mode = self.modal.motion
        if mode == G80:
            return  # axis words left unused: error 31
        self.axes_used = True
        if mode == G0:
            self._linear(MoveKind.RAPID)
            return
        self._require_feed()
        if mode == G1:
            self._linear(MoveKind.FEED)
        elif mode in (G2, G3):
            self._arc(mode == G2)
        else:
            self._probe(mode)

    def _require_feed(self) -> None:
        if self.modal.inverse_time and "F" not in self.words.values:
            raise CommandError(Error.UNDEFINED_FEED, "G93 inverse time: F is required on each move")
        if self.modal.feed <= 0.0:
            raise CommandError(Error.UNDEFINED_FEED, "feed rate undefined: give an F word")

    def target(self) -> list[float]:
        """The line's axis words as a machine target (units, G90/G91, G53, offsets applied)."""
        target = list(self.position)
        scale = self.geo.inch_scale if self.modal.inches else None
        machine = self.words.g("non_modal") == 530
        for i, value in self.words.axes.items():
            mm = value * scale[i] if scale else value
            if machine:
                target[i] = mm
            elif self.modal.incremental:
                target[i] += mm
            else:
                target[i] = mm + self.wco[i]
        return target

    def _feed_mm_s(self, length_mm: float) -> float:
        if self.modal.inverse_time:
            return length_mm * self.modal.feed / 60.0
        return self.modal.feed / 60.0

    def check_limits(self, target: Position) -> None:
        """Raise SoftLimitError when ``target`` is outside the travel."""
        why = self.geo.outside(target)
        if why is not None:
            raise SoftLimitError(why)

    def emit(self, target: Position, kind: MoveKind, feed_mm_s: float) -> None:
        """Queue a move to ``target`` (after the soft limit check); zero-length moves vanish."""
        self.check_limits(target)
        if target == self.position:
            return
        m = self.modal
        self.moves.append(Move(target, feed_mm_s, kind, m.tool_mode, m.s, self.line_number))
        self.position = target

    def _linear(self, kind: MoveKind) -> None:
        target = tuple(self.target())
        if kind is MoveKind.RAPID:
            self.emit(target, kind, math.inf)
        else:
            self.emit(target, kind, self._feed_mm_s(math.dist(target, self.position)))

    def _probe(self, mode: int) -> None:
        if not self.words.axes:
            raise CommandError(Error.NO_AXIS_WORDS, f"G{mode / 10:g} needs axis words")
        target = tuple(self.target())
        if target == self.position:
            raise CommandError(Error.INVALID_TARGET, "probe target equals the current position")
        self.emit(target, MoveKind.PROBE, self._feed_mm_s(math.dist(target, self.position)))
        params = {"towards": mode in (382, 383), "error_on_fail": mode in (382, 384)}
        self.moves.append(Sync(SyncKind.PROBE, params))

    # -- arcs --------------------------------------------------------------------------------
    def _plane(self) -> tuple[int, int]:
        names, index = PLANE_AXES[self.modal.plane], self.geo.axis_index
        if names[0] not in index or names[1] not in index:
            raise CommandError(
                Error.UNSUPPORTED, f"G{self.modal.plane} arcs need axes {names[0]} and {names[1]}"
            )
        return index[names[0]], index[names[1]]

    def _arc(self, clockwise: bool) -> None:
        plane = self._plane()
        start, end = self.position, tuple(self.target())
        values = self.words.values
        if "R" in values:
            self.values_used.add("R")
            self._need_plane_words(plane)
            r_mm = values["R"] * (MM_PER_INCH if self.modal.inches else 1.0)
            centre = arcs.radius_form_centre(start, end, plane, r_mm, clockwise)
        else:
            if not any(letter in values for letter in PLANE_OFFSETS[self.modal.plane]):
                self._need_plane_words(plane)
                raise CommandError(
                    Error.NO_OFFSETS_IN_PLANE, "G2/G3 needs an in-plane I/J/K offset"
                )
            self.values_used.update(set("IJK") & values.keys())
            centre = self._offset_centre(plane)
            arcs.check_offset_radius(start, end, plane, centre)
        points = arcs.chords(
            start, end, plane, centre, clockwise, self.geo.settings.arc_tolerance_mm
        )
        self._emit_chords(points)

    def _need_plane_words(self, plane: tuple[int, int]) -> None:
        axes = self.words.axes
        if not axes:
            raise CommandError(Error.NO_AXIS_WORDS, "G2/G3 needs axis words")
        if plane[0] not in axes and plane[1] not in axes:
            raise CommandError(
                Error.NO_AXIS_WORDS_IN_PLANE, "G2/G3 needs an axis word in the plane"
            )

    def _offset_centre(self, plane: tuple[int, int]) -> tuple[float, float]:
        values, unit = self.words.values, MM_PER_INCH if self.modal.inches else 1.0
        centre = []
        for axis, letter in zip(plane, PLANE_OFFSETS[self.modal.plane], strict=True):
            value = values.get(letter)
            if value is None:
                centre.append(self.position[axis])
            elif self.modal.arc_absolute:
                centre.append(value * unit + self.wco[axis])
            else:
                centre.append(self.position[axis] + value * unit)
        return centre[0], centre[1]

    def _emit_chords(self, points: list[Position]) -> None:
        for point in points:
            self.check_limits(point)
        previous, length = self.position, 0.0
        for point in points:
            length += math.dist(point, previous)
            previous = point
        feed = self._feed_mm_s(length)
        for point in points:
            self.emit(point, MoveKind.ARC, feed)

    # -- the end of the line -----------------------------------------------------------------
    def _check_unused(self) -> None:
        if self.words.axes and not self.axes_used:
            raise CommandError(Error.UNUSED_AXIS_WORDS, "axis words with no command to use them")
        unused = self.words.values.keys() - self.values_used - ALWAYS_USED
        if unused:
            raise CommandError(Error.UNUSED_VALUE_WORDS, f"unused words {' '.join(sorted(unused))}")

    def _program_flow(self) -> None:
        code, m = self.words.g("m_stop"), self.modal
        if code is None:
            return
        if code in (0, 1):
            self.after.append(Action(ActionName.PAUSE, {"optional": code == 1}, stops_motion=True))
            return
        if m.tool_mode is not ToolMode.OFF:
            self.after.append(Action(ActionName.SPINDLE, {"mode": ToolMode.OFF, "s": m.s}))
        if m.mist or m.flood:
            self.after.append(Action(ActionName.COOLANT, {"mist": False, "flood": False}))
        self.after.append(Action(ActionName.PROGRAM_END, {"code": code}, stops_motion=True))
        m.motion, m.plane, m.incremental, m.inverse_time, m.wcs = G1, 17, False, False, 0
        m.tool_mode, m.mist, m.flood = ToolMode.OFF, False, False
        self.wco = self.offsets.wco(0, self.geo.z_axis)
