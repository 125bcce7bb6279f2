"""Klipper's G-code as the front-ends send it, translated to motiond's (pure).

:func:`translate` turns one ``gcode/script`` (lines joined by newlines) into :data:`Step`
objects that :mod:`modules.klippy_api.session` carries out in order: motiond G-code lines run
through the ordered path of every sender; job and realtime steps act through the same controls
as every other source. What is translated:

- ``SDCARD_PRINT_FILE FILENAME=...``: play that stored job; ``PAUSE``, ``RESUME``,
  ``CANCEL_PRINT``: hold (a job pauses), resume, abort;
- ``G28 [X Y Z]``: home (``G28.2``); Klipper's G28 homes, Grbl's goes to a stored point;
- ``M220 S<percent>``, ``SET_VELOCITY_FACTOR FACTOR=<f>``: the feed override;
- ``_CLIENT_LINEAR_MOVE X=.. Y=.. Z=.. F=.. [ABSOLUTE=1]`` and the front-ends' jog sequence
  (``[SAVE_GCODE_STATE] G91 G1 X10 F6000 [RESTORE_GCODE_STATE|G90]``): one ``$J=`` jog, which
  a hold or jog cancel stops and which leaves the modal state alone;
- ``SET_GCODE_OFFSET [X|Y|Z=mm] [X|Y|Z_ADJUST=mm] [MOVE=1]``: the offset Klipper calls
  ``homing_origin`` (motiond's work offset) set or adjusted by the babystep ``M290`` (``P0``
  without ``MOVE=1``), during a job as part of it (see ``scripts._gcode_offset``);
- ``SET_PIN PIN=name VALUE=v``: a switch's own line (``M8``, ``M106 S..``), see
  :mod:`modules.klippy_api.outputs`;
- ``M117 text`` sets ``display_status.message``; ``HELP`` lists the commands;
  ``RESTART``/``FIRMWARE_RESTART``: ``$X`` (unlock), then the API connections close so the
  front-end starts afresh, as after Klipper's restart; ``M112``: emergency stop.

Everything else (``M84``, ``G0``, ``$$``...) is motiond's own G-code, unchanged; an
extended command motiond does not know is refused in Klipper's words
(``Unknown command:"FOO_BAR"``, :func:`klipper_error`), and so is ``SET_VELOCITY_LIMIT``
with values (motiond's limits are its configuration's; without values it reports them).

A script's lines are split at ``\n``, as Klipper's ``run_script`` splits them. A line longer
than :data:`LINE_LIMIT` characters (error 11, as on every other stream) or a number beyond
:data:`MAX_NUMBER` in a Klipper command is refused. A long script is translated in pieces of
about :data:`PIECE_CHARS` (:func:`pieces`, :func:`translate_piece`), so that the caller can
let the event loop run between them; :func:`stops_at_once` finds an ``M112`` line anywhere in
a script in one pass of the regular expression engine.
"""

from __future__ import annotations

import math
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass

from server.errors import CommandError, Error

JOG_MACRO = "_CLIENT_LINEAR_MOVE"
LINE_LIMIT = 256  # characters in one line, as the line protocol's (error:11)
MAX_NUMBER = 1e9  # mm, mm/min, percent: anything larger is a mistake or an attack
PIECE_CHARS = 4096  # a long script is translated this many characters at a time
HELP: dict[str, str] = {
    "SDCARD_PRINT_FILE": "Play a stored job: SDCARD_PRINT_FILE FILENAME=<name>",
    "PAUSE": "Pause the job (feed hold)",
    "RESUME": "Resume the paused job",
    "CANCEL_PRINT": "Abort the job",
    "G28": "Home all axes, or those named (G28 X Y)",
    "M84": "Motors off",
    "M220": "Feed override in percent: M220 S<10..200>",
    "SET_VELOCITY_FACTOR": "Feed override: SET_VELOCITY_FACTOR FACTOR=<0.1..2>",
    JOG_MACRO: "Jog: _CLIENT_LINEAR_MOVE X=<mm> Y=<mm> Z=<mm> F=<mm/min> [ABSOLUTE=1]",
    "M117": "Show a message on the display: M117 <text>",
    "SET_GCODE_OFFSET": "Work offset: SET_GCODE_OFFSET Z=<mm>|Z_ADJUST=<mm> [MOVE=1]",
    "SET_PIN": "Switch an output (air assist, fan): SET_PIN PIN=<name> VALUE=<0..1>",
    "SET_VELOCITY_LIMIT": "Report the velocity and acceleration limits (set in the config)",
    "M112": "Emergency stop",
    "RESTART": "Unlock after an alarm ($X) and reconnect",
    "FIRMWARE_RESTART": "Unlock after an alarm ($X) and reconnect",
    "HELP": "List the commands",
    "M114": "Report the position",
    "G0": "Rapid move", "G1": "Linear move", "G2": "Arc (clockwise)",
    "G3": "Arc (counter-clockwise)", "G4": "Dwell", "G90": "Absolute positioning",
    "G91": "Relative positioning", "G92": "Set the position", "M3": "Laser/spindle on",
    "M4": "Laser on, power follows speed", "M5": "Laser/spindle off",
}
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_NAME = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\s+(.*))?$", re.S)
_MOVE = re.compile(r"G0*[01]$")
# server.kernel.control.halts_at_once on every line of a script at once: a line (after \n)
# that starts, after blanks and a line number, with M112 (no other digit after it)
_M112_LINE = re.compile(r"^\s*(?:N\d+[^\S\n]*)?M[^\S\n]*0*112(?:\D|$)", re.I | re.M)
# Klipper's extended command: a name whose second character is no part of a number (G1 is a
# traditional command, FOO_BAR and SET_PIN extended ones).
_EXTENDED = re.compile(r"([A-Za-z_][A-Za-z_][A-Za-z0-9_]*)(?:\s|$)")
# Lines that move the machine: a jog, homing, G0-G3 anywhere (not G4, G10, G90...).
_MOTION_LINE = re.compile(r"^\s*(\$J=|\$H)|(?<![A-Z])G(28\.2|0*[0-3](?![\d.]))", re.I)
# motiond's errors for a line its parser could not read as G-code: a name nobody registered.
_NOT_GCODE = frozenset({Error.EXPECTED_COMMAND_LETTER, Error.BAD_NUMBER_FORMAT,
                        Error.UNKNOWN_COMMAND})


@dataclass(frozen=True, slots=True)
class Line:
    text: str  # motiond G-code, run as every sender's line


@dataclass(frozen=True, slots=True)
class StartJob:
    name: str


@dataclass(frozen=True, slots=True)
class Control:
    action: str  # pause, resume, cancel, estop, restart, help


@dataclass(frozen=True, slots=True)
class FeedOverride:
    percent: int


@dataclass(frozen=True, slots=True)
class Message:
    text: str | None


@dataclass(frozen=True, slots=True)
class GcodeOffset:
    """Klipper's ``SET_GCODE_OFFSET``: the new offset (mm) of the named axes, absolute or
    adjusted; ``move``: the head moves by the change so the work position stays."""

    absolute: dict[str, float]
    adjust: dict[str, float]
    move: bool
    speed_mm_s: float | None


@dataclass(frozen=True, slots=True)
class SetPin:
    """Klipper's ``SET_PIN PIN=name VALUE=v``: an output pin (a switch) to ``value`` (0..1)."""

    pin: str
    value: float


Step = Line | StartJob | Control | FeedOverride | Message | GcodeOffset | SetPin


def translate(script: str, jog_feed_mm_min: float) -> list[Step]:
    """One script's steps; raises :class:`CommandError` for a malformed Klipper command (and
    then nothing of the script runs)."""
    lines = _lines(script)
    jog = _jog_sequence(lines, jog_feed_mm_min)
    if jog is not None:
        return jog
    return [step for line in lines for step in _line(line, jog_feed_mm_min)]


def pieces(script: str, size_chars: int = PIECE_CHARS) -> Iterator[str]:
    """The script in pieces of whole lines: each ends at the first line end after
    ``size_chars`` characters (or with the script)."""
    start = 0
    while start < len(script):
        end = script.find("\n", start + size_chars)
        end = len(script) if end < 0 else end + 1
        yield script[start:end]
        start = end


def translate_piece(piece: str, jog_feed_mm_min: float) -> list[Step]:
    """The steps of some lines of a long script (the front-ends' jog sequence is a whole
    script of two to four lines: not looked for here)."""
    return [step for line in _lines(piece) for step in _line(line, jog_feed_mm_min)]


def stops_at_once(script: str) -> bool:
    """Whether a line of the script is an ``M112``, which acts on arrival (looked for line
    by line only in a script that holds ``112``: a fast search first)."""
    return "112" in script and _M112_LINE.search(script) is not None


def _lines(script: str) -> list[str]:
    lines = [line.strip() for line in script.split("\n")]
    for line in lines:
        if len(line) > LINE_LIMIT:
            raise CommandError(Error.LINE_OVERFLOW,
                               f"a line longer than {LINE_LIMIT} characters")
    return [line for line in lines if line]


def _line(text: str, jog_feed_mm_min: float) -> list[Step]:
    match = _NAME.match(text)
    if match is None:
        return [Line(text)]
    name, rest = match.group(1).upper(), match.group(2) or ""
    if name in ("PAUSE", "RESUME", "HELP"):
        return [Control(name.lower())]
    if name == "CANCEL_PRINT":
        return [Control("cancel")]
    if name in ("RESTART", "FIRMWARE_RESTART"):
        return [Control("restart")]
    if name == "M112":
        return [Control("estop")]
    if name == "M117":
        return [Message(rest.strip() or None)]
    if name == "SDCARD_PRINT_FILE":
        return [StartJob(_params(name, rest).get("FILENAME", "").lstrip("/"))]
    if name == "SET_VELOCITY_FACTOR":
        factor = _number(name, _params(name, rest), "FACTOR")
        if factor <= 0.0:
            raise CommandError(Error.UNSUPPORTED, f"{name}: FACTOR must be positive")
        return [FeedOverride(round(100 * factor))]
    if name == JOG_MACRO:
        return [Line(_client_move(_params(name, rest), jog_feed_mm_min))]
    if name == "SET_GCODE_OFFSET":
        return [_gcode_offset(_params(name, rest))]
    if name == "SET_PIN":
        params = _params(name, rest)
        return [SetPin(params.get("PIN", ""), _number(name, params, "VALUE"))]
    if name == "SET_VELOCITY_LIMIT":
        return [_velocity_limit(text, _params(name, rest))]
    if name in ("SAVE_GCODE_STATE", "RESTORE_GCODE_STATE"):
        raise CommandError(Error.UNSUPPORTED, f"{name}: only the front-ends' jog sequence "
                                              "(G91, one G0/G1, G90) is supported")
    words = dict(_WORD.findall(text.upper()))
    if name == "M220":
        return [FeedOverride(round(_number(name, {"S": words.get("S", "100")}, "S")))]
    if name == "G28":
        axes = [axis for axis in "XYZ" if axis in text.upper()[3:]]
        return [Line("G28.2" + "".join(f" {axis}0" for axis in axes))]
    return [Line(text)]


def _params(name: str, rest: str) -> dict[str, str]:
    """Klipper's ``KEY=VALUE`` parameters (values may be quoted)."""
    try:
        tokens = shlex.split(rest)
    except ValueError as exc:
        raise CommandError(Error.UNSUPPORTED, f"{name}: {exc}") from exc
    params: dict[str, str] = {}
    for token in tokens:
        key, sep, value = token.partition("=")
        if not sep:
            raise CommandError(Error.UNSUPPORTED, f"{name}: malformed parameter {token!r}")
        params[key.upper()] = value
    return params


def _number(name: str, params: dict[str, str], key: str) -> float:
    try:
        value = float(params[key])
    except (KeyError, ValueError) as exc:
        raise CommandError(Error.UNSUPPORTED, f"{name}: {key}=<number> required") from exc
    if not math.isfinite(value) or abs(value) > MAX_NUMBER:
        raise CommandError(Error.UNSUPPORTED, f"{name}: {key} must be a number within "
                                              f"+-{MAX_NUMBER:g}")
    return value


def _client_move(params: dict[str, str], jog_feed_mm_min: float) -> str:
    unknown = set(params) - {"X", "Y", "Z", "F", "ABSOLUTE"}
    if unknown:
        raise CommandError(Error.UNSUPPORTED, f"{JOG_MACRO}: no axis {', '.join(sorted(unknown))}")
    axes = {axis: _number(JOG_MACRO, params, axis) for axis in "XYZ" if axis in params}
    if not axes:
        raise CommandError(Error.UNSUPPORTED, f"{JOG_MACRO}: no axis to move")
    feed = _number(JOG_MACRO, params, "F") if "F" in params else jog_feed_mm_min
    mode = "G90" if params.get("ABSOLUTE", "0") not in ("0", "") else "G91"
    return _jog(mode, axes, feed)


def _velocity_limit(text: str, params: dict[str, str]) -> Control:
    """Without values, Klipper's report of the limits; with values, refused in Klipper's
    words: motiond plans with its configured limits (per axis, ``[axes.*]``)."""
    if params:
        raise CommandError(Error.UNSUPPORTED, f"Error on '{text}': motiond's velocity and "
                           "acceleration limits are its configuration's ([axes.*] "
                           "max_rate_mm_s, accel_mm_s2) and cannot change at run time")
    return Control("velocity_limit")


def velocity_report(max_velocity_mm_s: float, max_accel_mm_s2: float) -> str:
    """``SET_VELOCITY_LIMIT``'s answer, as Klipper's console shows it."""
    return (f"// max_velocity: {max_velocity_mm_s:.6f}\n// max_accel: {max_accel_mm_s2:.6f}\n"
            "// minimum_cruise_ratio: 0.500000\n// square_corner_velocity: 5.000000")


def check_line_during_job(text: str, job_state: str | None) -> None:
    """Refuse at once what would wait unanswered behind a job's lines: while the job is
    paused, any line (the job holds the ordered path until it resumes); while it runs, a
    front-end's motion (a jog, homing, a move: refused once its turn came). Klipper jogs in a
    pause; motiond's paused job keeps the machine and its planned path."""
    if job_state == "paused" or (job_state == "running" and _MOTION_LINE.search(text)):
        raise CommandError(Error.BUSY, f"the job is {job_state}: G-code from the console "
                           "waits for the job here. Resume or cancel the job first")


def klipper_error(text: str, exc: CommandError) -> CommandError:
    """A refused line's error as Klipper words it: an extended command motiond could not
    read as G-code is ``Unknown command:"NAME"``; any other error is unchanged."""
    match = _EXTENDED.match(text.strip())
    if match is None or exc.code not in _NOT_GCODE:
        return exc
    return CommandError(Error.UNKNOWN_COMMAND, f'Unknown command:"{match.group(1).upper()}"')


def _gcode_offset(params: dict[str, str]) -> GcodeOffset:
    name = "SET_GCODE_OFFSET"
    axes = {"X", "Y", "Z"}
    known = axes | {f"{axis}_ADJUST" for axis in axes} | {"MOVE", "MOVE_SPEED"}
    if set(params) - known:
        raise CommandError(Error.UNSUPPORTED,
                           f"{name}: no {', '.join(sorted(set(params) - known))} here")
    absolute = {axis: _number(name, params, axis) for axis in sorted(axes & set(params))}
    adjust = {axis: _number(name, params, f"{axis}_ADJUST") for axis in sorted(axes)
              if f"{axis}_ADJUST" in params}
    speed = _number(name, params, "MOVE_SPEED") if "MOVE_SPEED" in params else None
    if speed is not None and speed <= 0:
        raise CommandError(Error.UNSUPPORTED, f"{name}: MOVE_SPEED must be positive")
    return GcodeOffset(absolute, adjust, params.get("MOVE", "0") not in ("0", ""), speed)


def _jog(mode: str, axes: dict[str, float], feed_mm_min: float) -> str:
    words = " ".join(f"{axis}{value:g}" for axis, value in axes.items())
    return f"$J=G21 {mode} {words} F{feed_mm_min:g}"


def _jog_sequence(lines: list[str], jog_feed_mm_min: float) -> list[Step] | None:
    """The front-ends' jog: ``[SAVE_GCODE_STATE ..] G90|G91 G0|G1 <axes> [F] [RESTORE_GCODE_
    STATE ..|G90]`` as one jog (and the trailing G90, when sent without SAVE/RESTORE)."""
    upper = [line.upper() for line in lines]
    saved = bool(upper) and upper[0].startswith("SAVE_GCODE_STATE")
    if saved:
        if len(upper) < 2 or not upper[-1].startswith("RESTORE_GCODE_STATE"):
            return None
        upper = upper[1:-1]
    after: list[Step] = []
    if not saved and len(upper) == 3 and upper[2] == "G90":
        upper, after = upper[:2], [Line("G90")]
    if len(upper) != 2 or upper[0] not in ("G90", "G91"):
        return None
    command, _, rest = upper[1].partition(" ")
    if not _MOVE.match(command):
        return None
    words = _WORD.findall(rest)
    if not words or len(words) != len(rest.split()) or any(
            letter not in "XYZF" for letter, _ in words):
        return None
    numbers = dict(words)
    axes = {letter: _number("G1", numbers, letter) for letter in numbers if letter != "F"}
    feeds = [_number("G1", numbers, "F")] if "F" in numbers else []
    if not axes:
        return None
    feed = feeds[0] if feeds else jog_feed_mm_min
    return [Line(_jog(upper[0], axes, feed)), *after]
