"""A Grbl controller's status report, parsed strictly: the board is untrusted input.

A report is ``<State|Field:values|...>`` in printable ASCII. :func:`parse_status` accepts only
the states Grbl 1.1 (and grblHAL's ``Tool``) define, each field once, and numbers that are
finite and within what a real machine can report (:data:`BOUNDS`); anything else raises
:class:`ValueError`, and the caller counts and drops the report (noise on a USB line next to a
laser, a board printing half a line when it resets). Fields it does not know are ignored, as a
sender would (grblHAL and FluidNC add some).

Units: positions mm (or inches with ``$13=1``, as the board prints them), feed per minute.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass

STATES = frozenset({"Idle", "Run", "Hold:0", "Hold:1", "Jog", "Home", "Alarm", "Check",
                    "Door:0", "Door:1", "Door:2", "Door:3", "Sleep", "Tool"})
MAX_AXES = 6
MAX_POSITION = 1e6  # mm: a kilometre of travel is already beyond any machine
MAX_FEED = 1e6  # per minute
MAX_SPINDLE = 1e6
MAX_BLOCKS = 1024  # planner blocks free (Grbl 15, grblHAL up to a few hundred)
MAX_RX_BYTES = 65536  # receive buffer bytes free (Grbl 127, grblHAL 1023)
MAX_LINE_NUMBER = 9_999_999  # Grbl's N limit
OVERRIDE_BOUNDS = ((1, 255), (1, 100), (1, 255))  # feed, rapid, spindle percent
_FRAME = re.compile(r"^<([^|<>]+)((?:\|[^|<>]*)*)>$")
_PINS = re.compile(r"^[A-Z]*$")  # Grbl: XYZPDHRS (+ABC); grblHAL adds a few letters
_ACCESSORIES = re.compile(r"^[A-Z]*$")  # Grbl: SCFM
_NUMBER = re.compile(r"^[-+]?(?:\d+\.?\d*|\.\d+)$")


@dataclass(frozen=True, slots=True)
class ControllerStatus:
    """One ``<...>`` report, decoded. ``machine_mm`` is None if it carried no position."""

    state: str  # "Idle", "Run", "Hold:0", "Alarm", "Door:1"...
    machine_mm: tuple[float, ...] | None
    wco_mm: tuple[float, ...] | None
    feed_mm_min: float = 0.0
    spindle_s: float = 0.0
    planner_free_blocks: int | None = None
    rx_free_bytes: int | None = None
    line_number: int | None = None
    pins: str = ""
    overrides: tuple[int, int, int] | None = None
    accessories: str = ""

    @property
    def base_state(self) -> str:
        """The state without its sub-state: ``Hold:0`` -> ``Hold``."""
        return self.state.partition(":")[0]


def parse_status(text: str, wco_mm: tuple[float, ...] | None = None) -> ControllerStatus:
    """Decode ``<Idle|MPos:1,2,3|FS:0,0|WCO:0,0,0>``; ``wco_mm``: the last offset reported
    (Grbl sends ``WCO:`` only now and then), used to turn ``WPos:`` into machine position.
    Raises ValueError for anything a healthy board does not send."""
    frame = _FRAME.match(text)
    if frame is None or not text.isascii() or not text.isprintable():
        raise ValueError(f"not a status report: {text!r}")
    state = frame.group(1)
    if state not in STATES:
        raise ValueError(f"unknown state {state!r}")
    values = _fields(frame.group(2))
    wco = _axes(values["WCO"]) if "WCO" in values else None
    feed, spindle = _feed(values)
    blocks, rx_bytes = _buffers(values.get("Bf"))
    return ControllerStatus(
        state=state,
        machine_mm=_machine_position(values, wco or wco_mm),
        wco_mm=wco,
        feed_mm_min=feed,
        spindle_s=spindle,
        planner_free_blocks=blocks,
        rx_free_bytes=rx_bytes,
        line_number=_line_number(values.get("Ln")),
        pins=_letters(values.get("Pn", ""), _PINS),
        overrides=_overrides(values.get("Ov")),
        accessories=_letters(values.get("A", ""), _ACCESSORIES),
    )


def _fields(text: str) -> dict[str, str]:
    values: dict[str, str] = {}
    for item in text.split("|")[1:]:
        key, _, value = item.partition(":")
        if key in values:
            raise ValueError(f"field {key} twice")
        values[key] = value
    return values


def _machine_position(
    values: Mapping[str, str], wco_mm: tuple[float, ...] | None
) -> tuple[float, ...] | None:
    if "MPos" in values:
        return _axes(values["MPos"])
    if "WPos" in values:
        work = _axes(values["WPos"])
        offset = wco_mm or tuple(0.0 for _ in work)
        return tuple(w + o for w, o in zip(work, offset, strict=False))
    return None


def _axes(text: str) -> tuple[float, ...]:
    numbers = numbers_in(text, MAX_POSITION)
    if not 1 <= len(numbers) <= MAX_AXES:
        raise ValueError(f"{len(numbers)} axes in {text!r}")
    return numbers


def _feed(values: Mapping[str, str]) -> tuple[float, float]:
    if "FS" in values:
        numbers = numbers_in(values["FS"], MAX_FEED)
        if len(numbers) != 2 or min(numbers) < 0:
            raise ValueError(f"bad FS:{values['FS']}")
        return numbers[0], numbers[1]
    if "F" in values:
        (feed,) = numbers_in(values["F"], MAX_FEED)
        if feed < 0:
            raise ValueError(f"bad F:{values['F']}")
        return feed, 0.0
    return 0.0, 0.0


def _buffers(text: str | None) -> tuple[int | None, int | None]:
    if text is None:
        return None, None
    blocks, rx_bytes = _ints(text, 2)
    if not (0 <= blocks <= MAX_BLOCKS and 0 <= rx_bytes <= MAX_RX_BYTES):
        raise ValueError(f"Bf:{text} out of range")
    return blocks, rx_bytes


def _line_number(text: str | None) -> int | None:
    if text is None:
        return None
    (number,) = _ints(text, 1)
    if not 0 <= number <= MAX_LINE_NUMBER:
        raise ValueError(f"Ln:{text} out of range")
    return number


def _overrides(text: str | None) -> tuple[int, int, int] | None:
    if text is None:
        return None
    feed, rapid, spindle = _ints(text, 3)
    for value, (low, high) in zip((feed, rapid, spindle), OVERRIDE_BOUNDS, strict=True):
        if not low <= value <= high:
            raise ValueError(f"Ov:{text} out of range")
    return feed, rapid, spindle


def _ints(text: str, count: int) -> tuple[int, ...]:
    parts = text.split(",")
    if len(parts) != count or not all(part.lstrip("-").isdigit() for part in parts):
        raise ValueError(f"expected {count} integers in {text!r}")
    return tuple(int(part) for part in parts)


def _letters(text: str, allowed: re.Pattern[str]) -> str:
    if not allowed.match(text):
        raise ValueError(f"unexpected letters {text!r}")
    return text


def numbers_in(text: str, bound: float) -> tuple[float, ...]:
    """Comma-separated decimal numbers of magnitude at most ``bound``; ValueError for anything
    else (``nan``, ``1e999``, ``1e308``, an empty field)."""
    parts = text.split(",")
    if not all(_NUMBER.match(part) for part in parts):
        raise ValueError(f"not decimal numbers: {text!r}")
    numbers = tuple(float(part) for part in parts)
    if not all(math.isfinite(n) and abs(n) <= bound for n in numbers):
        raise ValueError(f"a number out of range in {text!r}")
    return numbers
