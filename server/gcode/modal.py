"""The interpreter's state and the first step of reading a line: words -> :class:`Words`.

Pure data and functions, no I/O. :class:`ModalState` is the G-code modal state (the part
``$G`` reports), :class:`Offsets` the coordinate data (the part ``$#`` reports). Both are
replaced, never shared, when a line commits, so the interpreter can work on copies and throw
them away when a line is refused.

G codes are identified by ten times their number, an ``int``: ``G1`` is 10, ``G38.2`` is 382,
``G59.1`` is 591. That keeps look-ups exact for the dotted codes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from server.errors import CommandError, Error
from server.motion.moves import Position, ToolMode

if TYPE_CHECKING:
    from server.gcode.codes import CodeTable

MM_PER_INCH = 25.4
MAX_TOOL_NUMBER = 255
WCS_COUNT = 9  # G54..G59, G59.1..G59.3


G0, G1, G2, G3, G80 = 0, 10, 20, 30, 800
PROBES = (382, 383, 384, 385)
WCS_CODES = (540, 550, 560, 570, 580, 590, 591, 592, 593)

G_GROUPS: dict[int, str] = {
    **dict.fromkeys((G0, G1, G2, G3, *PROBES, G80), "motion"),
    **dict.fromkeys((40, 100, 280, 281, 282, 300, 301, 530, 920, 921, 922, 923), "non_modal"),
    **dict.fromkeys((170, 180, 190), "plane"),
    **dict.fromkeys((200, 210), "units"),
    400: "cutter",
    **dict.fromkeys((431, 490), "tool_length"),
    **dict.fromkeys(WCS_CODES, "wcs"),
    **dict.fromkeys((610, 611, 640), "path"),
    **dict.fromkeys((900, 910), "distance"),
    **dict.fromkeys((901, 911), "arc_distance"),
    **dict.fromkeys((930, 940), "feed_mode"),
}
M_GROUPS: dict[int, str] = {
    **dict.fromkeys((0, 1, 2, 30), "stop"),
    **dict.fromkeys((3, 4, 5), "spindle"),
    6: "tool_change",
    **dict.fromkeys((7, 8, 9), "coolant"),
    **dict.fromkeys((17, 18, 84), "motors"),
    **dict.fromkeys((112, 114, 400, 410, 999), "sync"),
    290: "offset",  # babystep: takes the line's axis words (see LineExecutor.babystep)
}
# Commands that use axis words; two on one line are error 24 (G80 uses none).
AXIS_COMMANDS = frozenset((G0, G1, G2, G3, *PROBES, 100, 280, 282, 300, 920, 431, 490))
VALUE_LETTERS = frozenset("FSTPLRIJK")
NEGATIVE_FORBIDDEN = frozenset("FSTP")


@dataclass(slots=True)
class ModalState:
    """The modal state of Grbl's ``$G`` (power-on defaults).

    ``feed`` is mm/min under G94 and the inverse-time value (1/min) under G93; 0 is undefined.
    """

    motion: int = G0
    plane: int = 17
    inches: bool = False
    incremental: bool = False
    arc_absolute: bool = False
    inverse_time: bool = False
    wcs: int = 0
    tool_mode: ToolMode = ToolMode.OFF
    mist: bool = False
    flood: bool = False
    tool: int = 0
    feed: float = 0.0
    s: float = 0.0

    def copy(self) -> ModalState:
        """A shallow copy (all fields are immutable values)."""
        return ModalState(
            self.motion,
            self.plane,
            self.inches,
            self.incremental,
            self.arc_absolute,
            self.inverse_time,
            self.wcs,
            self.tool_mode,
            self.mist,
            self.flood,
            self.tool,
            self.feed,
            self.s,
        )


@dataclass(slots=True)
class Offsets:
    """Coordinate data in machine mm: WCS G54..G59.3, G28/G30, G92 (and saved), TLO, probe."""

    wcs: tuple[Position, ...]
    g28: Position
    g30: Position
    g92: Position
    g92_saved: Position
    tlo_mm: float = 0.0
    probe: Position = ()
    probe_ok: bool = False

    @classmethod
    def zero(cls, axes: int) -> Offsets:
        """All offsets zero for a machine with ``axes`` axes."""
        origin = (0.0,) * axes
        return cls((origin,) * WCS_COUNT, origin, origin, origin, origin, 0.0, origin)

    def copy(self) -> Offsets:
        """A shallow copy (all fields are immutable values)."""
        return Offsets(
            self.wcs,
            self.g28,
            self.g30,
            self.g92,
            self.g92_saved,
            self.tlo_mm,
            self.probe,
            self.probe_ok,
        )

    def wco(self, wcs: int, z_axis: int | None) -> Position:
        """Work coordinate offset: the WCS ``wcs`` + G92 + tool length offset on Z."""
        wco = [a + b for a, b in zip(self.wcs[wcs], self.g92, strict=True)]
        if z_axis is not None:
            wco[z_axis] += self.tlo_mm
        return tuple(wco)


@dataclass(slots=True)
class Words:
    """The words of one line, classified (Grbl's step 1), before any meaning is applied.

    Attributes:
        groups: modal group name -> G code x10 (``"motion": 10``) or M code (``"m_stop": 30``).
        values: the F S T P L R I J K words.
        axes: axis index -> value as written (program units).
        module_codes: M-codes owned by modules (:mod:`server.gcode.codes`), in line order.
    """

    groups: dict[str, int] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)
    axes: dict[int, float] = field(default_factory=dict)
    module_codes: list[int] = field(default_factory=list)

    def g(self, group: str) -> int | None:
        """The code of ``group`` on this line, or None."""
        return self.groups.get(group)


def read_words(
    words: list[tuple[str, float]], axis_index: dict[str, int], codes: CodeTable | None = None
) -> Words:
    """Classify a line's words; raise the word-level errors (20, 21, 23, 24, 25, 4, 38)."""
    block = Words()
    for letter, value in words:
        if letter == "G":
            code = _g_code(value)
            if code[1] in AXIS_COMMANDS and _axis_command(block) is not None:
                raise CommandError(  # Grbl checks this before the modal groups
                    Error.AXIS_COMMAND_CONFLICT, "two commands on one line use axis words")
            _add_group(block, "g", code)
        elif letter == "M":
            _add_m_code(block, value, codes)
        elif letter in axis_index:
            index = axis_index[letter]
            if index in block.axes:
                raise CommandError(Error.REPEATED_WORD, f"repeated {letter} word")
            block.axes[index] = value
        elif letter in VALUE_LETTERS:
            _add_value(block, letter, value)
        else:
            raise CommandError(Error.UNSUPPORTED, _unknown_letter(letter))
    commands = [
        code
        for name, code in block.groups.items()
        if not name.startswith("m_") and code in AXIS_COMMANDS
    ]
    if len(commands) + ("m_offset" in block.groups) > 1:
        raise CommandError(Error.AXIS_COMMAND_CONFLICT, "two commands on one line use axis words")
    return block


def _axis_command(block: Words) -> int | None:
    """The command of the line so far that takes the axis words, if any."""
    for name, code in block.groups.items():
        if not name.startswith("m_") and code in AXIS_COMMANDS:
            return code
    return None


def _unknown_letter(letter: str) -> str:
    if letter in "XYZABCUVW":
        return f"axis {letter} is not configured on this machine"
    if letter == "E":
        return "E (extruder) words are not supported: this is not a 3D printer"
    if letter == "O":
        return "O-codes (subroutines and flow control) are not supported"
    if letter in "DH":
        return f"{letter} words (tool offset tables) are not supported"
    return f"unsupported word {letter}"


def _add_group(block: Words, kind: str, code: tuple[str, int]) -> None:
    group, number = code
    key = group if kind == "g" else f"m_{group}"
    if key in block.groups:
        raise CommandError(
            Error.MODAL_GROUP_VIOLATION, f"two commands of the {group} group on a line"
        )
    block.groups[key] = number


def _g_code(value: float) -> tuple[str, int]:
    code = round(value * 10)
    if abs(value * 10 - code) < 1e-6 and code in G_GROUPS:
        return G_GROUPS[code], code
    if value in (41, 42):
        raise CommandError(
            Error.UNSUPPORTED, f"G{value:g} cutter radius compensation is not supported"
        )
    if value == 73 or 81 <= value <= 89:
        raise CommandError(Error.UNSUPPORTED, f"G{value:g} canned cycles are not supported")
    whole = int(value) * 10
    if value != int(value) and whole in G_GROUPS and int(value) not in _DECIMAL_G_CODES:
        raise CommandError(Error.INTEGER_REQUIRED, f"G{value:g}: G{int(value)} has no decimals")
    raise CommandError(Error.UNSUPPORTED, f"unsupported G code G{value:g}")


# G codes whose decimals Grbl reads itself (G28.1, G38.2, G43.1, G92.1): others are error 20.
_DECIMAL_G_CODES = frozenset({28, 30, 38, 43, 92})


def _add_m_code(block: Words, value: float, codes: CodeTable | None) -> None:
    if value != int(value):
        raise CommandError(Error.INTEGER_REQUIRED, f"M{value:g}: M codes are integers")
    code = int(value)
    if code in M_GROUPS:
        _add_group(block, "m", (M_GROUPS[code], code))
    elif codes is not None and codes.owns(code):
        _add_group(block, "m", (f"module:{codes.group(code)}", code))
        block.module_codes.append(code)
    else:
        raise CommandError(Error.UNSUPPORTED, f"unsupported M code M{code}")


def _add_value(block: Words, letter: str, value: float) -> None:
    if letter in block.values:
        raise CommandError(Error.REPEATED_WORD, f"repeated {letter} word")
    if letter in NEGATIVE_FORBIDDEN and value < 0:
        raise CommandError(Error.NEGATIVE_VALUE, f"negative {letter} value")
    if letter in "TL" and value != int(value):
        raise CommandError(Error.INTEGER_REQUIRED, f"{letter}{value:g}: an integer is required")
    if letter == "T" and value > MAX_TOOL_NUMBER:
        raise CommandError(
            Error.TOOL_NUMBER, f"T{value:g}: tool numbers go up to {MAX_TOOL_NUMBER}"
        )
    block.values[letter] = value + 0.0  # -0.0 -> 0.0


@dataclass(frozen=True, slots=True)
class InterpreterSettings:
    """What the interpreter needs to know about the machine.

    Attributes:
        axis_names: configured axes in machine order, a subset of XYZABC, e.g. ``("X","Y","Z")``.
        min_mm, max_mm: travel per axis in machine coordinates (mm; degrees for A/B/C).
        soft_limits: refuse targets outside the travel (Grbl ``$20``).
        arc_tolerance_mm: largest distance between a chord and its arc (Grbl ``$12``).
        report_inches: ``$13``; reports of positions (``$#``) in inches.
        spin_up_delay_s: motion waits this long after M3/M4 starts a stopped spindle.
    """

    axis_names: tuple[str, ...]
    min_mm: tuple[float, ...]
    max_mm: tuple[float, ...]
    soft_limits: bool = True
    arc_tolerance_mm: float = 0.002
    report_inches: bool = False
    spin_up_delay_s: float = 0.0

    def __post_init__(self) -> None:
        names = self.axis_names
        if any(name not in "XYZABC" or len(name) != 1 for name in names):
            raise ValueError(f"axis names must be among X Y Z A B C, not {names}")
        if len(set(names)) != len(names):
            raise ValueError(f"an axis is named twice in {names}")
        if not len(self.min_mm) == len(self.max_mm) == len(names):
            raise ValueError("min_mm and max_mm need one value per axis")
        if self.arc_tolerance_mm <= 0:
            raise ValueError("arc_tolerance_mm must be positive")


SOFT_LIMIT_SLACK_MM = 1e-9


@dataclass(frozen=True, slots=True)
class Geometry:
    """Look-up tables derived once from :class:`InterpreterSettings` for the hot path.

    ``inch_scale`` converts program inches to machine units per axis (rotary A/B/C axes are in
    degrees and are not scaled by G20).
    """

    settings: InterpreterSettings
    axis_index: dict[str, int]
    z_axis: int | None
    inch_scale: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    @classmethod
    def of(cls, settings: InterpreterSettings) -> Geometry:
        """The tables for ``settings``."""
        names = settings.axis_names
        return cls(
            settings,
            {name: i for i, name in enumerate(names)},
            names.index("Z") if "Z" in names else None,
            tuple(MM_PER_INCH if name in "XYZ" else 1.0 for name in names),
            tuple(v - SOFT_LIMIT_SLACK_MM for v in settings.min_mm),
            tuple(v + SOFT_LIMIT_SLACK_MM for v in settings.max_mm),
        )

    def inside(self, target: Position) -> bool:
        """Whether ``target`` lies within the travel (whatever the soft limits setting): the
        hot path's test; :meth:`outside` says why not."""
        for low, value, high in zip(self.low, target, self.high):  # noqa: B905, SIM110 - (faster)
            if not low <= value <= high:  # (also false for NaN)
                return False
        return True

    def outside(self, target: Position) -> str | None:
        """Why ``target`` is outside the travel (when soft limits are on), or None."""
        if not self.settings.soft_limits:
            return None
        for i, value in enumerate(target):
            if not self.low[i] <= value <= self.high[i]:
                s = self.settings
                return (
                    f"{s.axis_names[i]}{value:.3f} outside the travel "
                    f"[{s.min_mm[i]:g}, {s.max_mm[i]:g}]"
                )
        return None
