"""``M290`` (babystep) for a Grbl 1.1 board, which does not know it (pure).

motiond's interpreter reads ``M290 Z0.05`` as: the G92 offset of Z grows by 0.05, the tool
moves by it at the rapid rate (``P0``: it stays), the modes are unchanged. A Grbl board
answers ``error:20`` to it, so :func:`babystep_lines` says the same with lines Grbl 1.1
runs, computed from motiond's interpreter *after* it read the ``M290``:

1. ``G53G0Z<machine target>`` (``P1`` only): the move, in machine coordinates. G53 is
   non-modal and takes absolute machine values whatever G90/G91 (gcode.c: the coordinate
   system and the distance mode are not applied under ``NON_MODAL_ABSOLUTE_OVERRIDE``);
   ``G0`` needs no feed, also under G93. It sets the modal motion mode to G0.
2. ``G92Z<work position>``: the G92 offset, computed by the board from the position its
   parser holds (the move's target), as motiond computed it. G92 values are absolute and in
   program units. Grbl refuses any axis word under G80 (``error:31``, even G92's), so a
   ``P0`` under G80 first sends ``G0``.
3. The motion mode as it was: nothing after G0; a bare ``G1`` (gcode.c: a motion mode
   without axis words is accepted and moves nothing, if a feed rate is defined, which under
   G93 needs an F word on the line); ``G80``. An arc (``G2``/``G3``) or a probe (``G38.x``)
   cannot be restored without axis words, nor ``G1`` with no feed rate (F0, or G93): the
   ``M290`` is refused with a clear error before anything is sent.

Values are in the program's units (G20: inches, rotary axes in degrees), with 4 decimals in
mm and 6 in inches (Grbl reads 8 significant digits: far below a step). The line may hold
only ``M290``, its axis words, ``P`` and ``N``: anything else would need its own translation.
"""

from __future__ import annotations

from server.errors import CommandError, Error
from server.gcode.interpreter import Interpreter
from server.gcode.modal import Geometry
from server.gcode.parser import Line

BABYSTEP = 290.0
_RESTORE = {"G0": "", "G1": "G1", "G80": "G80"}  # the line that brings each mode back


def is_babystep(line: Line) -> bool:
    """The line has ``M290`` (the cheap tests first: this runs for every line)."""
    return BABYSTEP in line.values and "M" in line.letters and ("M", BABYSTEP) in line.words


def babystep_lines(line: Line, interpreter: Interpreter) -> list[str]:
    """The Grbl 1.1 lines that do what the ``M290`` ``line`` did in ``interpreter`` (which
    has just read it); raises :class:`CommandError` for a line or a mode they cannot match."""
    names = interpreter.settings.axis_names
    axes = [names.index(letter) for letter, _ in line.words if letter in names]
    if set(line.letters) - set(names) - {"M", "P"} or line.letters.count("M") != 1:
        raise CommandError(Error.UNSUPPORTED, "on a Grbl board M290 goes on a line of its "
                           "own: M290, axis words and P only")
    modes = interpreter.modal_snapshot()
    move = "P" not in line.letters or line.values[line.letters.index("P")] != 0.0
    restore = _restore_line(str(modes["motion"]), modes, move)
    scale = Geometry.of(interpreter.settings).inch_scale if modes["units"] == "in" else None
    wco, position = interpreter.wco(), interpreter.position

    def words(values: tuple[float, ...]) -> str:
        return "".join(names[i] + _number(values[i], scale[i] if scale else 1.0)
                       for i in sorted(set(axes)))

    work = tuple(p - w for p, w in zip(position, wco, strict=True))
    # the move; else, under G80 only, a G0 first (Grbl refuses G92's axis words under G80)
    first = [f"G53G0{words(position)}"] if move else ["G0"] if restore else []
    return [*first, f"G92{words(work)}", *([restore] if restore else [])]


def _restore_line(motion: str, modes: dict[str, object], move: bool) -> str:
    """The line that brings ``motion`` back after a ``G0`` (empty: none needed)."""
    if not move and motion != "G80":
        return ""  # G92 alone changes no mode
    if motion not in _RESTORE:
        raise CommandError(Error.UNSUPPORTED, f"M290 on a Grbl board: its motion mode {motion} "
                           "cannot be restored after the move (send G0 or G1 first, or P0)")
    if motion == "G1" and (modes["feed_mode"] == "inverse_time" or not modes["feed_mm_min"]):
        raise CommandError(Error.UNDEFINED_FEED, "M290 on a Grbl board: G1 cannot be restored "
                           "after the move without a feed rate (G94 and an F first, or P0)")
    return _RESTORE[motion]


def _number(value_mm: float, scale: float) -> str:
    """A value in program units (``scale``: mm per unit), to 0.0001 mm or 0.000001 in,
    without trailing zeros."""
    text = f"{value_mm / scale:.4f}" if scale == 1.0 else f"{value_mm / scale:.6f}"
    text = text.rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text
