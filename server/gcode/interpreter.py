"""The G-code interpreter: modal state -> moves in machine millimetres (pure: no asyncio, no I/O).

:class:`Interpreter` takes parsed :class:`~server.gcode.parser.Line` objects and returns,
in the order they must run, :class:`~server.motion.moves.Move` (absolute machine mm, mm/s), ordered
:class:`~server.motion.moves.Action` (spindle, coolant, dwell, pause, program end, tool change,
motors) and :class:`~server.motion.moves.Sync` requests for the dispatcher (M114, M112, M999, probe,
G28.2 homing). It follows Grbl 1.1 (error numbers, order of execution, ``$G``/``$#``) with a
few LinuxCNC/Smoothieware additions. Conventions worth knowing:

* A refused line raises :class:`~server.errors.CommandError` (Grbl numbering) and changes
  nothing: the general path works on copies and commits only on success. A target outside the
  travel raises :class:`~server.errors.SoftLimitError` before any output.
* ``G4 P`` is in **seconds** (Grbl, LinuxCNC); a missing P is error 28.
* Feed: F is units/min under G94 (remembered in mm/min); under G93 it is 1/min and required
  on every G1/G2/G3/G38 line, each move then lasting ``60/F`` seconds. Rapids use
  ``feed_mm_s = inf`` (the planner caps them at the axes' max rates).
* Arcs are cut into chords within ``arc_tolerance_mm`` (end point exact); IJK arcs whose end
  equals the start are full circles, also with no axis words at all (``G2 I10 J0``).
* Follow actions (spindle/S, coolant, ...) that come just before a move on the same line ride
  in that move's ``actions``, where the planner would attach them anyway; only actions with no
  move after them are outputs of their own.
* Zero-length moves produce no :class:`Move`. After a probe the position is the probe target
  until the dispatcher calls :meth:`Interpreter.set_position`; G28.2 leaves it unchanged.
* Beyond Grbl: G59.1-G59.3 (``G10 P7..P9``), G90.1 absolute arc centres, G92.2/G92.3
  (LinuxCNC), G28.2 homing (Smoothieware), M6, M17/M18/M84, M112, M114, M400 (wait for
  motion), M410 (quickstop), M999, M290 (babystep). Rotary axes
  A/B/C are in degrees and are not scaled by G20. ``$#`` lists G54-G59 only (as Grbl), G80 does
  not forbid axis words that a G10/G28/G30/G92 on the same line uses, and soft reset clears
  the G92 and tool length offsets (as Grbl) but keeps the stored coordinate systems.
"""

from __future__ import annotations

import enum
import math
from typing import Any

import numpy as np

from server.errors import CommandError, Error
from server.gcode.codes import CodeTable
from server.gcode.executor import LineExecutor
from server.gcode.modal import (
    G0,
    G1,
    M_GROUPS,
    MM_PER_INCH,
    WCS_CODES,
    Geometry,
    InterpreterSettings,
    ModalState,
    Offsets,
    read_words,
)
from server.gcode.parser import Line
from server.gcode.plain import PlainRun, plain_run, takes_runs
from server.motion.moves import Action, ActionName, Move, MoveKind, Output, Position, ToolMode

__all__ = ["Interpreter", "InterpreterSettings", "InterpreterState"]

# What a line can change: modal state, offsets, position, work offset (see Interpreter.save).
InterpreterState = tuple[ModalState, Offsets, Position, Position]

_FEED, _RAPID = MoveKind.FEED, MoveKind.RAPID

JOG_G_CODES = {200: "units", 210: "units", 900: "distance", 910: "distance", 530: "machine"}
MOTION_NAMES = {
    0: "G0",
    10: "G1",
    20: "G2",
    30: "G3",
    382: "G38.2",
    383: "G38.3",
    384: "G38.4",
    385: "G38.5",
    800: "G80",
}


CORE_QUERIES = frozenset({114, 400})  # M114 reports the position, M400 waits: both change nothing
UNLOCKING = frozenset({112, 410, 999})  # M112 halts, M410 stops, M999 clears: all run in ALARM


class LineKind(enum.Enum):
    """What a line may do, decided from all of its words (not its first one).

    ``QUERY`` lines only report: read-only connections and a locked machine may run them. A
    line of M codes nobody knows (``M21``, which RepRap hosts send on connect) is a query too:
    it is refused as unsupported whatever the state, so a locked machine answers it as an
    idle one does.
    ``UNLOCK`` lines (M112, M999, G28.2 homing) run while the machine is locked, but only from
    a connection that may control it. Every other line is an ``EFFECT``.
    """

    QUERY = "query"
    UNLOCK = "unlock"
    EFFECT = "effect"


_EFFECT = LineKind.EFFECT


class Interpreter:
    """Modal G-code state and the conversion of lines to machine moves; see the module doc.

    Attributes:
        position: the last commanded machine position (mm, one value per axis).
        codes: the M-codes modules own (shared with every interpreter of this machine).
    """

    def __init__(self, settings: InterpreterSettings, codes: CodeTable | None = None) -> None:
        self.codes = codes if codes is not None else CodeTable()
        self._geo = Geometry.of(settings)
        self._modal = ModalState()
        self._offsets = Offsets.zero(len(settings.axis_names))
        self._wco: Position = self._offsets.wco(0, self._geo.z_axis)
        self.position: Position = (0.0,) * len(settings.axis_names)

    @property
    def settings(self) -> InterpreterSettings:
        """The machine settings; assigning new ones takes effect on the next line."""
        return self._geo.settings

    @settings.setter
    def settings(self, settings: InterpreterSettings) -> None:
        if settings.axis_names != self._geo.settings.axis_names:
            self._offsets = Offsets.zero(len(settings.axis_names))
            self.position = (0.0,) * len(settings.axis_names)
        self._geo = Geometry.of(settings)
        self._wco = self._offsets.wco(self._modal.wcs, self._geo.z_axis)

    # -- executing lines ---------------------------------------------------------------------
    def execute(self, line: Line) -> list[Output]:
        """Execute one parsed line.

        Returns:
            Moves, actions and sync requests in the order they must run.

        Raises:
            CommandError: the line is invalid (Grbl error number); nothing changed.
            SoftLimitError: a target lies outside the travel; nothing changed.
        """
        if line.error is not None:
            raise line.error
        if line.block_delete or not line.letters:
            return []
        outputs = self._fast_line(line)
        if outputs is None:
            outputs = self._general_line(line)
        return outputs

    def takes_runs(self) -> bool:
        """Whether :meth:`execute_plain` takes lines from this state (not under G91 or G93)."""
        return takes_runs(self._geo, self._modal)

    def execute_plain(self, columns: dict[str, np.ndarray], start: int, stop: int) -> PlainRun:
        """Execute the plain lines ``start`` to ``stop`` of a chunk parsed by
        :func:`~server.gcode.parser.parse_plain` (its ``columns``) at once, up to the first
        one the one-line fast path would not take (see :mod:`server.gcode.plain`): the same
        moves and state as :meth:`execute` of each."""
        run = plain_run(self._geo, self._modal, self._wco, self.position,
                        {letter: values[start:stop] for letter, values in columns.items()},
                        stop - start)
        if run.count:
            self.rewind(run, run.count)  # (to the state after the whole run)
        return run

    def rewind(self, run: PlainRun, lines: int) -> None:
        """Back to the state after the first ``lines`` lines of ``run``, the last run
        executed (:meth:`execute_plain`): the lines after them are read again later (a live
        job's span that the planner had no room for whole)."""
        modal = self._modal
        self.position, modal.motion, modal.feed, modal.s = run.after(lines)

    def runs_state(self) -> tuple[object, ...]:
        """Everything :meth:`execute_plain` reads: equal states read the same lines alike."""
        modal = self._modal
        return (self.position, self._wco, self._geo, modal.motion, modal.feed, modal.s,
                modal.tool_mode, modal.inches, modal.incremental, modal.inverse_time)

    def classify(self, line: Line) -> LineKind:
        """What ``line`` may do (see :class:`LineKind`); unknown words count as effects.

        Cheap for the common line: without an M word and a ``G28.2`` it is an effect."""
        letters, values = line.letters, line.values
        if "M" not in letters and not ("G" in letters and 28.2 in values):
            return _EFFECT
        words = [(letter, value) for letter, value in zip(letters, values, strict=True)
                 if letter != "N"]
        m_codes = [value for letter, value in words if letter == "M"]
        if len(m_codes) == len(words):
            if all(self._is_query(code) for code in m_codes):
                return LineKind.QUERY
            if all(code in UNLOCKING or self._is_query(code) for code in m_codes):
                return LineKind.UNLOCK
            return LineKind.EFFECT
        homing = [value for letter, value in words if letter == "G"] == [28.2]
        axes = {letter for letter, _ in words} - {"G"} <= set(self._geo.axis_index)
        return LineKind.UNLOCK if homing and axes else LineKind.EFFECT

    def _is_query(self, code: float) -> bool:
        if code != int(code):
            return False
        known = int(code) in M_GROUPS or self.codes.owns(int(code))
        return not known or code in CORE_QUERIES or self.codes.is_query(int(code))

    def _general_line(self, line: Line) -> list[Output]:
        words = read_words(line.words, self._geo.axis_index, self.codes)
        executor = LineExecutor(
            self._geo, self._modal, self._offsets, self.position, words, line.line_number,
            self.codes,
        )
        outputs = executor.run()
        self._modal, self._offsets = executor.modal, executor.offsets
        self.position, self._wco = executor.position, executor.wco
        return _fold_follow_actions(outputs)

    def _fast_line(self, line: Line) -> list[Output] | None:
        """G0/G1 + axis + F + S lines under G94 without surprises; None sends the line to the
        general path (which also produces every error)."""
        modal = self._modal
        if modal.inverse_time:
            return None
        geo = self._geo
        index, scale = geo.axis_index, geo.inch_scale if modal.inches else None
        motion, explicit, feed, s = modal.motion, False, None, None
        target: list[float] | None = None
        for letter, value in zip(line.letters, line.values):  # noqa: B905 - parallel lists
            i = index.get(letter)
            if i is not None:  # the parser refuses repeated axis words
                if target is None:
                    target, incremental, wco = list(self.position), modal.incremental, self._wco
                mm = value * scale[i] if scale else value
                target[i] = target[i] + mm if incremental else mm + wco[i]
            elif letter == "S":
                if value < 0.0:
                    return None
                s = value + 0.0
            elif letter == "G" and not explicit and (value == 0.0 or value == 1.0):
                motion, explicit = (G0 if value == 0.0 else G1), True
            elif letter == "F" and value >= 0.0:
                feed = value * MM_PER_INCH + 0.0 if modal.inches else value + 0.0
            else:
                return None
        if motion != G1 and motion != G0:
            return None
        feed_mm_min = modal.feed if feed is None else feed
        if motion == G1 and (target or explicit) and feed_mm_min <= 0.0:
            return None
        end = None if target is None else tuple(target)
        if end is not None and geo.settings.soft_limits and not geo.inside(end):
            return None
        mode = modal.tool_mode
        actions: list[Action] = []
        if s is not None and s != modal.s:
            actions = [Action(ActionName.SPINDLE, {"mode": mode, "s": s})]
            modal.s = s
        modal.motion, modal.feed = motion, feed_mm_min
        if end is None or end == self.position:
            return list(actions)
        self.position = end
        if motion == G1:
            return [Move(end, feed_mm_min / 60.0, _FEED, mode, modal.s, line.line_number, actions)]
        return [Move(end, math.inf, _RAPID, mode, modal.s, line.line_number, actions)]

    # -- jogging -----------------------------------------------------------------------------
    def jog(self, line: Line) -> list[Move]:
        """Execute the body of a ``$J=`` command (already parsed as a Line).

        Axis words and F are required; G20/G21, G90/G91 and G53 may appear and apply to this
        jog only. The modal state is not changed; the position becomes the jog target.

        Raises:
            CommandError: 16 for an invalid jog, 15 when the target exceeds the travel.
        """
        if line.error is not None:
            raise line.error
        modes, axes, feed = self._jog_words(line)
        inches = modes["units"] == 200 if "units" in modes else self._modal.inches
        incremental = modes["distance"] == 910 if "distance" in modes else self._modal.incremental
        target = list(self.position)
        for i, value in axes.items():
            mm = value * self._geo.inch_scale[i] if inches else value
            if "machine" in modes:
                target[i] = mm
            else:
                target[i] = target[i] + mm if incremental else mm + self._wco[i]
        why = self._geo.outside(tuple(target))
        if why is not None:
            raise CommandError(Error.JOG_TRAVEL_EXCEEDED, f"jog target exceeds the travel: {why}")
        if tuple(target) == self.position:
            return []
        self.position = tuple(target)
        feed_mm_s = feed * (MM_PER_INCH if inches else 1.0) / 60.0
        m = self._modal
        return [Move(self.position, feed_mm_s, MoveKind.JOG, m.tool_mode, m.s, line.line_number)]

    def _jog_words(self, line: Line) -> tuple[dict[str, int], dict[int, float], float]:
        modes: dict[str, int] = {}
        axes: dict[int, float] = {}
        feed: float | None = None
        for letter, value in line.words:
            if letter in self._geo.axis_index and self._geo.axis_index[letter] not in axes:
                axes[self._geo.axis_index[letter]] = value
            elif letter == "F" and feed is None:
                if value < 0:
                    raise CommandError(Error.NEGATIVE_VALUE, "negative F value")
                feed = value
            elif (
                letter == "G" and (code := round(value * 10)) in JOG_G_CODES and code == value * 10
            ):
                group = JOG_G_CODES[code]
                if group in modes:
                    raise CommandError(
                        Error.MODAL_GROUP_VIOLATION, f"two {group} commands in a jog"
                    )
                modes[group] = code
            else:
                raise CommandError(Error.INVALID_JOG, f"{letter}{value:g} is not allowed in a jog")
        if not feed:
            raise CommandError(Error.UNDEFINED_FEED, "a jog needs a positive F")
        if not axes:
            raise CommandError(Error.INVALID_JOG, "a jog needs axis words")
        return modes, axes, feed

    # -- saving and restoring -----------------------------------------------------------------
    def save(self) -> InterpreterState:
        """Everything a line can change, for :meth:`restore` (a downstream board that refuses
        a line motiond accepted: its state did not change, so motiond's must not either)."""
        return self._modal.copy(), self._offsets, self.position, self._wco

    def restore(self, state: InterpreterState) -> None:
        """Back to what :meth:`save` returned (the settings are not part of it)."""
        modal, self._offsets, self.position, self._wco = state
        self._modal = modal.copy()

    # -- position, offsets and probing -------------------------------------------------------
    def set_position(self, machine_mm: Position) -> None:
        """Resynchronise after a halt, reset, probe or homing: the machine is at ``machine_mm``."""
        self.position = tuple(float(v) for v in machine_mm)

    def work_position(self, machine_mm: Position) -> Position:
        """``machine_mm`` in the active work coordinate system (mm)."""
        return tuple(m - w for m, w in zip(machine_mm, self._wco, strict=True))

    def wco(self) -> Position:
        """Work coordinate offset (mm): active WCS + G92 + tool length offset on Z."""
        return self._wco

    def state_key(self) -> str:
        """A fingerprint of everything a job read from here depends on (position, modal
        state, offsets): equal keys read the same file the same way."""
        return repr((self.position, self._modal, self._offsets, self.settings))

    def record_probe(self, machine_mm: Position, success: bool) -> None:
        """Remember the last probe result for ``$#`` (``[PRB:...]``)."""
        offsets = self._offsets.copy()
        offsets.probe, offsets.probe_ok = tuple(float(v) for v in machine_mm), success
        self._offsets = offsets

    def adopt_offsets(self, points: dict[str, Position], tlo_mm: float | None = None) -> None:
        """Take the stored points another controller reports (``$#``: ``G28``, ``G30`` and
        ``G92``, machine mm, missing axes zero) and its tool length offset as this one's."""
        offsets = self._offsets.copy()
        axes = len(self.position)
        for name, point in points.items():
            value = tuple(float(v) for v in point[:axes]) + (0.0,) * (axes - len(point))
            setattr(offsets, name.lower(), value)
        if tlo_mm is not None:
            offsets.tlo_mm = float(tlo_mm)
        self._offsets = offsets
        self._wco = offsets.wco(self._modal.wcs, self._geo.z_axis)

    def reset(self) -> None:
        """Soft reset (Ctrl-X): Grbl's power-on modal state; G92 and the tool length offset are
        cleared, stored coordinate systems, G28/G30, the probe result and the position kept."""
        self._modal = ModalState()
        offsets = self._offsets.copy()
        offsets.g92 = offsets.g92_saved = (0.0,) * len(self.position)
        offsets.tlo_mm = 0.0
        self._offsets = offsets
        self._wco = offsets.wco(0, self._geo.z_axis)

    def tools_off(self) -> None:
        """Every stop (M410, M112, an alarm, a reset): the spindle or laser off with no power
        (M5 S0) and the coolant off (M9) in the modal state, as a reset board has them, so
        the next move does not switch them on again; everything else is kept."""
        modal = self._modal.copy()
        modal.tool_mode, modal.s, modal.mist, modal.flood = ToolMode.OFF, 0.0, False, False
        self._modal = modal

    # -- reports -----------------------------------------------------------------------------
    def gc_report(self) -> str:
        """Grbl's ``$G`` line, e.g. ``[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]``.

        F is in mm/min whatever G20/G21, in/min with ``$13=1``, as Grbl 1.1 reports it."""
        m = self._modal
        coolant = " ".join(c for c, on in (("M7", m.mist), ("M8", m.flood)) if on) or "M9"
        inches = self.settings.report_inches and not m.inverse_time
        feed = m.feed / MM_PER_INCH if inches else m.feed
        return (
            f"[GC:{MOTION_NAMES[m.motion]} {_wcs_name(m.wcs)} G{m.plane} "
            f"G{20 if m.inches else 21} G{91 if m.incremental else 90} "
            f"G{93 if m.inverse_time else 94} M{int(m.tool_mode)} {coolant} T{m.tool} "
            f"F{_number(feed)} S{_number(m.s)}]"
        )

    def offsets_report(self) -> list[str]:
        """Grbl's ``$#`` lines: G54-G59, G28, G30, G92, TLO and PRB (inches with ``$13=1``)."""
        o = self._offsets
        names = [_wcs_name(i) for i in range(6)] + ["G28", "G30", "G92"]
        points = [*o.wcs[:6], o.g28, o.g30, o.g92]
        lines = [f"[{name}:{self._coords(p)}]" for name, p in zip(names, points, strict=True)]
        lines.append(f"[TLO:{self._coords((o.tlo_mm,))}]")
        lines.append(f"[PRB:{self._coords(o.probe)}:{int(o.probe_ok)}]")
        return lines

    def _coords(self, point: Position) -> str:
        if self.settings.report_inches:
            return ",".join(f"{v / MM_PER_INCH:.4f}" for v in point)
        return ",".join(f"{v:.3f}" for v in point)

    def modal_snapshot(self) -> dict[str, Any]:
        """The modal state as JSON-able values (for the web UI and the status API)."""
        m = self._modal
        return {
            "motion": MOTION_NAMES[m.motion],
            "units": "in" if m.inches else "mm",
            "distance": "incremental" if m.incremental else "absolute",
            "arc_distance": "absolute" if m.arc_absolute else "incremental",
            "feed_mode": "inverse_time" if m.inverse_time else "units_per_min",
            "wcs": _wcs_name(m.wcs),
            "plane": f"G{m.plane}",
            "feed_mm_min": m.feed,
            "s": m.s,
            "tool_mode": f"M{int(m.tool_mode)}",
            "tool": m.tool,
            "coolant": {"mist": m.mist, "flood": m.flood},
        }


def _wcs_name(index: int) -> str:
    return f"G{WCS_CODES[index] / 10:g}"


def _number(value: float) -> str:
    """A report number: no decimals when whole, else up to three."""
    return f"{value:.0f}" if value == int(value) else f"{value:.3f}".rstrip("0")


def _fold_follow_actions(outputs: list[Output]) -> list[Output]:
    """Follow actions just before a move ride in that move's ``actions``: they take effect
    where it starts, exactly as the planner would attach them."""
    folded: list[Output] = []
    waiting: list[Action] = []
    for output in outputs:
        if type(output) is Action and output.lead_s <= 0.0 and not output.stops_motion:
            waiting.append(output)
            continue
        if type(output) is Move:
            output.actions[:0] = waiting
        else:
            folded += waiting
        waiting = []
        folded.append(output)
    return folded + waiting
