"""Pure formatting of Grbl 1.1 reports (and the Smoothie ``M114`` position line).

Nothing here does I/O or keeps machine state: each function turns values into the exact text a
Grbl sender expects, without the line ending (:meth:`server.protocol.lines.LineProtocol.push` and
``reply_ok`` add it). Formats follow Grbl 1.1h ``report.c``:

* status report ``<State|MPos:x,y,z|Bf:b,r|Ln:n|FS:f,s|Pn:p|WCO:x,y,z|Ov:f,r,s|A:a>``, fields in
  that order; positions with 3 decimals in mm, 4 in inches; feed in mm/min with no decimals, or
  in/min with one; spindle speed with no decimals;
* ``A:`` (accessories) only ever rides along with ``Ov:``, like in Grbl;
* ``$$`` settings as ``$n=value``, ``$I`` as ``[VER:1.1h.<build>:<info>]`` + ``[OPT:<letters>,
  <blocks>,<bytes>]``, ``$`` help as one ``[HLP:...]`` line, alarms as ``ALARM:n``;
* for RepRap hosts, errors worded like Marlin (:func:`format_reprap_error`).

:class:`StatusScheduler` decides, per connection, when a report carries ``WCO:`` and ``Ov:``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from server.errors import ALARM_MEANINGS, ERROR_MEANINGS, Error

GRBL_VERSION = "1.1h"
UNLOCK_HINT = "[MSG:'$H'|'$X' to unlock]"  # Grbl's, after the banner of a reset in alarm
MM_PER_INCH = 25.4

# Grbl 1.1 status report mask ($10) bits.
REPORT_MPOS = 1
REPORT_BUFFER = 2

# Grbl config.h defaults: a busy machine refreshes the slow-changing fields less often.
WCO_REFRESH_BUSY = 30
WCO_REFRESH_IDLE = 10
OV_REFRESH_BUSY = 20
OV_REFRESH_IDLE = 10
BUSY_STATES = frozenset({"Run", "Hold", "Jog", "Home", "Door"})

# Marlin's wording of communication errors: OctoPrint recognises these and resends.
REPRAP_RESEND_TEXT: dict[int, str] = {
    Error.CHECKSUM: "checksum mismatch",
    Error.LINE_NUMBER_SEQUENCE: "Line Number is not Last Line Number+1",
}
# Errors after which a job cannot go on: OctoPrint stops the job on an ``Error:`` line. A target
# outside the travel is not one: Marlin clamps it, and the host's next lines still run.
# A line refused in alarm is not one: OctoPrint would send M112 and go offline on the first
# click (Home, a jog); it gets ``echo:`` naming the alarm and M999, then ``ok``.
REPRAP_FATAL_ERRORS = frozenset({Error.AUTH_REQUIRED})
REPRAP_UNLOCK = "M999 to unlock"
NOTIFY = "//action:notification "  # OctoPrint shows these (its bundled notification plugin)
REPRAP_UNKNOWN_COMMAND_ERRORS = frozenset({Error.UNSUPPORTED, Error.UNKNOWN_COMMAND})


@dataclass(frozen=True, slots=True)
class StatusSnapshot:
    """What one status report shows. Positions in mm (machine coordinates), speeds in mm/s.

    Attributes:
        state: ``Idle``, ``Run``, ``Hold:0``/``Hold:1``, ``Jog``, ``Home``, ``Alarm``, ``Check``,
            ``Door:0``..``Door:3`` or ``Sleep``.
        machine_mm: machine position per axis, mm.
        wco_mm: work coordinate offset per axis (work = machine - wco), mm.
        feed_mm_s: current tool speed, mm/s.
        spindle_s: current spindle speed or laser power, S units.
        planner_free_blocks: free planner blocks (``Bf`` first value).
        rx_free_bytes: free bytes in this connection's input buffer (``Bf`` second value).
        line_number: the ``N`` of the executing block, or None.
        pins: triggered inputs in Grbl order, e.g. ``"PXYZDRHS"``; empty when none.
        overrides: feed %, rapid %, spindle %.
        accessories: ``S`` (spindle CW) or ``C`` (CCW), ``F`` flood, ``M`` mist; empty when off.
    """

    state: str
    machine_mm: tuple[float, ...]
    wco_mm: tuple[float, ...]
    feed_mm_s: float
    spindle_s: float
    planner_free_blocks: int
    rx_free_bytes: int
    line_number: int | None
    pins: str
    overrides: tuple[int, int, int]
    accessories: str


def format_coords(values_mm: Sequence[float], *, inches: bool = False) -> str:
    """Comma-separated coordinates: 3 decimals in mm, 4 in inches; never ``-0.000``."""
    if inches:
        return ",".join(_fixed(value / MM_PER_INCH, 4) for value in values_mm)
    return ",".join(_fixed(value, 3) for value in values_mm)


def format_status(
    snap: StatusSnapshot,
    *,
    report_mask: int = REPORT_MPOS,
    inches: bool = False,
    include_wco: bool = False,
    include_ov: bool = False,
) -> str:
    """The Grbl 1.1 status report for ``snap``, e.g. ``<Idle|MPos:0.000,0.000,0.000|FS:0,0>``.

    Args:
        snap: what to report.
        report_mask: Grbl ``$10``: bit 0 set reports ``MPos``, clear reports ``WPos``;
            bit 1 adds ``Bf:``.
        inches: Grbl ``$13=1``: positions in inches, feed in in/min.
        include_wco: add ``WCO:`` (see :class:`StatusScheduler`).
        include_ov: add ``Ov:`` and, when any accessory is on, ``A:``.
    """
    fields = [snap.state, _position_field(snap, report_mask, inches)]
    if report_mask & REPORT_BUFFER:
        fields.append(f"Bf:{snap.planner_free_blocks},{snap.rx_free_bytes}")
    if snap.line_number:
        fields.append(f"Ln:{snap.line_number}")
    fields.append(f"FS:{_feed(snap.feed_mm_s, inches)},{_fixed(snap.spindle_s, 0)}")
    if snap.pins:
        fields.append(f"Pn:{snap.pins}")
    if include_wco:
        fields.append(f"WCO:{format_coords(snap.wco_mm, inches=inches)}")
    if include_ov:
        feed, rapid, spindle = snap.overrides
        fields.append(f"Ov:{feed},{rapid},{spindle}")
        if snap.accessories:
            fields.append(f"A:{snap.accessories}")
    return "<" + "|".join(fields) + ">"


class StatusScheduler:
    """Decides, per connection, which status reports carry ``WCO:`` and ``Ov:`` (Grbl's rules).

    A field is sent when its value changed since it was last sent, and otherwise every
    ``WCO_REFRESH_*``/``OV_REFRESH_*`` reports (more often when idle, like Grbl's config.h
    defaults). A report that carries ``WCO:`` defers ``Ov:`` to the next one, keeping each
    report short. The first report carries ``WCO:``, the second ``Ov:``.
    """

    def __init__(self) -> None:
        self._wco_countdown = 0
        self._ov_countdown = 0
        self._sent_wco: tuple[float, ...] | None = None
        self._sent_ov: tuple[tuple[int, int, int], str] | None = None

    def refresh(self) -> None:
        """Send both fields again as soon as possible (e.g. after a reset)."""
        self._sent_wco = None
        self._sent_ov = None

    def schedule(self, snap: StatusSnapshot) -> tuple[bool, bool]:
        """``(include_wco, include_ov)`` for the report about to be sent; call once per report."""
        busy = snap.state.partition(":")[0] in BUSY_STATES
        if snap.wco_mm != self._sent_wco:
            self._wco_countdown = 0
        if (snap.overrides, snap.accessories) != self._sent_ov:
            self._ov_countdown = 0
        include_wco = self._wco_countdown == 0
        if include_wco:
            self._wco_countdown = WCO_REFRESH_BUSY if busy else WCO_REFRESH_IDLE
            self._sent_wco = snap.wco_mm
            self._ov_countdown = max(self._ov_countdown, 1)
        self._wco_countdown -= 1
        include_ov = self._ov_countdown == 0
        if include_ov:
            self._ov_countdown = OV_REFRESH_BUSY if busy else OV_REFRESH_IDLE
            self._sent_ov = (snap.overrides, snap.accessories)
        self._ov_countdown -= 1
        return include_wco, include_ov

    def report(
        self, snap: StatusSnapshot, *, report_mask: int = REPORT_MPOS, inches: bool = False
    ) -> str:
        """The next status report for this connection: :func:`format_status` on schedule."""
        include_wco, include_ov = self.schedule(snap)
        return format_status(
            snap,
            report_mask=report_mask,
            inches=inches,
            include_wco=include_wco,
            include_ov=include_ov,
        )


def format_settings(values: Mapping[int, float | int]) -> list[str]:
    """``$$`` lines, sorted by number: ``$0=10``, ``$11=0.010``; ints plain, floats 3 decimals."""
    return [f"${number}={_setting_value(values[number])}" for number in sorted(values)]


GRBL_PLANNER_BLOCKS = 15  # what Grbl 1.1h's $I reports: its 16-block buffer less one


def sender_blocks(free: int, capacity: int) -> int:
    """Free planner blocks on the scale ``$I`` reports (Grbl's 15 for a deeper planner), so
    ``Bf:`` shows the ``$I`` count exactly when the planner is empty and 0 when it is full:
    what senders compare it with."""
    shown = min(capacity, GRBL_PLANNER_BLOCKS)
    return max(0, free) * shown // capacity if capacity > 0 else 0


def format_help() -> str:
    """The ``$`` help line."""
    return "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"


def format_build_info(
    version: str,
    planner_blocks: int,
    rx_bytes: int,
    *,
    build_info: str = "",
    options: str = "VL",
) -> list[str]:
    """The ``$I`` lines: ``[VER:<version>:<build_info>]`` and ``[OPT:<options>,<blocks>,
    <bytes>]``.

    Args:
        version: e.g. ``1.1h.motiond-0.1.0``; senders read the Grbl version from its start, so
            ``1.1h.`` is put in front of a version that does not start with it.
        planner_blocks: planner blocks a sender may fill (Grbl reports its buffer size - 1).
        rx_bytes: the input buffer size character-counting senders must stay under.
        build_info: the user text Grbl stores with ``$I=``.
        options: Grbl build option letters (``V`` variable spindle, ``L`` no lock at power-up...).
    """
    if not version.startswith(GRBL_VERSION):
        version = f"{GRBL_VERSION}.{version}"
    return [
        f"[VER:{version}:{build_info}]",
        f"[OPT:{options},{planner_blocks},{rx_bytes}]",
    ]


def format_reprap_error(code: int, message: str, last_line: int) -> list[str]:
    """The Marlin-style answer to a refused line for RepRap hosts (printrun, OctoPrint).

    Always ends with ``ok`` (one reply per line) and never starts with ``error:``, which makes
    OctoPrint disconnect:

    * 41/42: ``Error:checksum mismatch, Last Line: <last_line>`` (or ``Error:Line Number is not
      Last Line Number+1, Last Line: ..``), ``Resend: <last_line + 1>``, ``ok`` -- Marlin's
      exact lines; OctoPrint treats them as recoverable, printrun resends.
    * 46 (not allowed): ``Error:<text> (code N)``, ``ok``.
    * 9 (alarm lock): ``//action:notification <text>``, ``echo:<text> (code 9)``, ``ok``:
      OctoPrint shows the alarm and M999 and keeps the connection.
    * 20, 43 with a message: ``echo:Unknown command: "<message>"``, ``ok``, as Marlin.
    * anything else: ``echo:<text> (code N)``, ``ok``.
    """
    if code in REPRAP_RESEND_TEXT:
        error = f"Error:{REPRAP_RESEND_TEXT[code]}, Last Line: {last_line}"
        return [error, f"Resend: {last_line + 1}", "ok"]
    if code in REPRAP_FATAL_ERRORS:
        return [f"Error:{_describe(code, message)}", "ok"]
    if code == Error.LOCKED_OUT:
        plain = _one_line(message or ERROR_MEANINGS.get(code, "Locked"))
        return [f"{NOTIFY}{plain}", f"echo:{plain} (code {code})", "ok"]
    if code in REPRAP_UNKNOWN_COMMAND_ERRORS and message:
        return [f'echo:Unknown command: "{_one_line(message)}"', "ok"]
    return [f"echo:{_describe(code, message)}", "ok"]


def format_lock(alarm_code: int) -> str:
    """The alarm that locks G-code out, named for people: ``ALARM:9 (Homing fail: ...)``."""
    meaning = ALARM_MEANINGS.get(alarm_code)
    return f"ALARM:{alarm_code} ({meaning})" if meaning else f"ALARM:{alarm_code}"


def format_reprap_notices(message: str) -> list[str]:
    """What a RepRap host (OctoPrint) is told beside a pushed line: an alarm and an unlock as
    ``//action:notification``, which OctoPrint shows its user; nothing for other lines."""
    if message.startswith("ALARM:") and message[6:].isdigit():
        return [f"{NOTIFY}{format_lock(int(message[6:]))}: {REPRAP_UNLOCK}"]
    if message == "[MSG:Caution: Unlocked]":
        return [f"{NOTIFY}Unlocked"]
    return []


def format_alarm(code: int) -> str:
    """The pushed alarm line, ``ALARM:<code>``; :data:`ALARM_MEANINGS` explains the code."""
    return f"ALARM:{code}"


def format_position_m114(
    machine_mm: Sequence[float],
    work_mm: Sequence[float],
    axis_names: Sequence[str] = ("X", "Y", "Z"),
    *,
    subcode: int = 0,
    inches: bool = False,
) -> str:
    """Smoothieware's ``M114`` text (sent after ``ok``): ``C: X:1.0000 Y:2.0000 Z:0.0000``.

    ``subcode`` follows Smoothie: 0 (``M114``) the work position as ``C:``, 1 (``M114.1``) the
    work position as ``WCS:``, 2 (``M114.2``) the machine position as ``MCS:``. Values have 4
    decimals, in mm or (``inches``, after G20) in inches.
    """
    prefix, values = {0: ("C:", work_mm), 1: ("WCS:", work_mm), 2: ("MCS:", machine_mm)}[subcode]
    scale = MM_PER_INCH if inches else 1.0
    pairs = zip(axis_names, values, strict=False)
    words = [f"{name}:{_fixed(value / scale, 4)}" for name, value in pairs]
    return " ".join([prefix, *words])


def _position_field(snap: StatusSnapshot, report_mask: int, inches: bool) -> str:
    if report_mask & REPORT_MPOS:
        return f"MPos:{format_coords(snap.machine_mm, inches=inches)}"
    work = [m - w for m, w in zip(snap.machine_mm, snap.wco_mm, strict=True)]
    return f"WPos:{format_coords(work, inches=inches)}"


def _feed(feed_mm_s: float, inches: bool) -> str:
    per_minute_mm = feed_mm_s * 60.0
    if inches:
        return _fixed(per_minute_mm / MM_PER_INCH, 1)
    return _fixed(per_minute_mm, 0)


def _setting_value(value: float | int) -> str:
    if isinstance(value, int):  # bool included: True -> 1
        return str(int(value))
    return _fixed(value, 3)


def _describe(code: int, message: str) -> str:
    return f"{_one_line(message or ERROR_MEANINGS.get(code, 'Command refused'))} (code {code})"


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _fixed(value: float, decimals: int) -> str:
    """``value`` with ``decimals`` decimals; a value that rounds to zero prints without sign."""
    rounded = round(value, decimals) + 0.0
    return f"{rounded:.{decimals}f}"

