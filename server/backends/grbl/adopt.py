"""What motiond takes from a Grbl board when it connects (``[backend] kind = "grbl"``).

The board is the machine: its ``$$`` settings (steps, rates, accelerations, travel, junction
deviation, laser mode), its machine coordinate space and soft limits, its work offsets and
stored positions (``$#``) and its modal state (``$G``) become motiond's, so the lines motiond
checks before sending them are judged as the board will judge them.

Grbl's machine space: with homing enabled (``$22=1``) the origin is at the switches and the
travel runs from 0 towards ``-$130``, ``-$131``...; soft limits (``$20=1``, which Grbl only
accepts with homing) refuse any target outside ``[-travel, 0]``. With homing off there are no
soft limits on the board, and motiond checks none unless its config file asks for them
(``[machine] soft_limits = true`` written out: then within the configured travel).
"""

from __future__ import annotations

import logging
import re

from server.backends.grbl.controller import Handshake
from server.backends.grbl.link import adopted_numbers, mismatches
from server.config import CoreConfig
from server.errors import CommandError
from server.gcode.interpreter import Interpreter
from server.gcode.modal import MM_PER_INCH
from server.gcode.parser import MAX_MAGNITUDE, parse_line
from server.machine.settings import Settings

log = logging.getLogger("motiond.grbl")
SOFT_LIMITS, HOMING = 20, 22
_WCS_REPORT = re.compile(r"^\[G(5[4-9]):([-0-9.,]+)\]$")
_POINT_REPORT = re.compile(r"^\[(G28|G30|G92|TLO):([-0-9.,]+)\]$")
_ADOPTED_MODES = frozenset({"G54", "G55", "G56", "G57", "G58", "G59", "G17", "G18", "G19",
                            "G20", "G21", "G90", "G91", "G93", "G94"})


def adopt_settings(settings: Settings, board: dict[int, float], axis_count: int) -> None:
    """Take the controller's steps, rates, accelerations, travel, junction deviation and
    laser mode; warn about each value that differs from motiond's config."""
    numbers = adopted_numbers(axis_count)
    for number, mine, theirs in mismatches(board, settings.values(), numbers):
        description = settings.table[number].description
        log.warning("controller $%d=%g (%s) differs from motiond's config (%g): using "
                    "the controller's", number, theirs, description, mine)
        try:
            settings.set(number, theirs)
        except CommandError as exc:
            log.warning("cannot adopt $%d=%g: %s", number, theirs, exc.message)


def adopt_space(core: CoreConfig, board: dict[int, float], *, keep_soft_limits: bool) -> None:
    """The board's machine space (``$22``) and soft limits (``$20``); see the module
    docstring. ``keep_soft_limits``: motiond's config file set ``soft_limits`` itself."""
    homing = board.get(HOMING, 0.0) >= 1
    if homing:
        for axis in core.axes.values():
            travel_mm = axis.max_mm - axis.min_mm
            axis.min_mm = min(axis.min_mm, -travel_mm)  # first: max > min all along
            axis.max_mm = 0.0
            axis.min_mm = -travel_mm
    if not keep_soft_limits:
        core.machine.soft_limits = homing and board.get(SOFT_LIMITS, 0.0) >= 1


def adopt_offsets(interpreter: Interpreter, axis_names: tuple[str, ...] | list[str],
                  handshake: Handshake) -> None:
    """The board's work offsets (``$#``: G54-G59, kept in its EEPROM) and modal state
    (``$G``: coordinate system, plane, units, distance and feed modes), run through
    motiond's interpreter as G-code, so work positions and soft limits agree."""
    inches = handshake.settings.get(13, 0.0) >= 1  # $13=1: $# reports inches
    lines = ["G20" if inches else "G21"]
    for text in handshake.offsets:
        match = _WCS_REPORT.match(text)
        if match:
            values = [float(v) for v in match.group(2).split(",") if v]
            words = " ".join(f"{axis}{value:.4f}" for axis, value in
                             zip(axis_names, values, strict=False))
            lines.append(f"G10 L2 P{int(match.group(1)) - 53} {words}")
    modal = [word for text in handshake.modal for word in text.strip("[]").split()[1:]
             if word in _ADOPTED_MODES]
    lines.append(" ".join(modal or ["G21"]))
    for line in lines:
        try:
            interpreter.execute(parse_line(line))
        except CommandError as exc:
            log.warning("cannot adopt the controller's %r: %s", line, exc.message)
    _adopt_points(interpreter, handshake, MM_PER_INCH if inches else 1.0)


def _adopt_points(interpreter: Interpreter, handshake: Handshake, mm_per_unit: float) -> None:
    """The board's G28/G30 positions, G92 offset and tool length offset (``$#``)."""
    points: dict[str, tuple[float, ...]] = {}
    tlo_mm = None
    for text in handshake.offsets:
        match = _POINT_REPORT.match(text)
        if match is None:
            continue
        try:
            values = tuple(float(v) * mm_per_unit for v in match.group(2).split(",") if v)
        except ValueError:
            log.warning("cannot read the controller's %r", text)
            continue
        if not all(abs(v) <= MAX_MAGNITUDE for v in values):  # also refuses nan and inf
            log.warning("cannot adopt the controller's %r: out of range", text)
            continue
        if match.group(1) == "TLO":
            tlo_mm = values[0] if values else None
        else:
            points[match.group(1)] = values
    interpreter.adopt_offsets(points, tlo_mm)
