"""The Grbl host's small pure parts: the realtime bytes that take an override to a value, what
reads as a board's answer, and the errors motiond answers for the board."""

from __future__ import annotations

from collections.abc import Sequence

from server.errors import CommandError, Error
from server.protocol.events import Realtime

# (100 %, +10, -10, +1, -1) for feed and spindle overrides
FEED_BYTES = (Realtime.FEED_100, Realtime.FEED_PLUS_10, Realtime.FEED_MINUS_10,
               Realtime.FEED_PLUS_1, Realtime.FEED_MINUS_1)
SPINDLE_BYTES = (Realtime.SPINDLE_100, Realtime.SPINDLE_PLUS_10, Realtime.SPINDLE_MINUS_10,
                  Realtime.SPINDLE_PLUS_1, Realtime.SPINDLE_MINUS_1)


def override_bytes(percent: int, steps: tuple[Realtime, ...]) -> list[int]:
    """The realtime bytes that take an override from anything to ``percent``."""
    hundred, plus_10, minus_10, plus_1, minus_1 = steps
    tens, ones = divmod(abs(percent - 100), 10)
    up = percent >= 100
    return [hundred, *[plus_10 if up else minus_10] * tens, *[plus_1 if up else minus_1] * ones]


def an_answer(text: str) -> bool:
    return text[:1] in "oOeE" and (text.lower() == "ok" or text.lower().startswith("error:"))


def axes_of(values: Sequence[float], count: int) -> tuple[float, ...]:
    """``values`` for ``count`` axes: cut, or completed with zeros."""
    return (*values[:count], *(0.0,) * (count - len(values)))


def mixed_line_error(code: float) -> CommandError:
    """A line mixing motiond's own M-code with words for the board: Grbl's answer to the code
    (20 unsupported; 23 for a number it cannot hold, M256 and up, as on the rig)."""
    number = Error.INTEGER_REQUIRED if code >= 256 else Error.UNSUPPORTED
    return CommandError(number, "M105, M114, M115, M400 and M999 are motiond's own: send "
                        "them on a line of their own")


def controller_error(code: int, text: str) -> CommandError:
    try:
        return CommandError(code, f"the controller refused {text!r}")
    except ValueError:  # a grblHAL or FluidNC number motiond does not know
        return CommandError(Error.UNSUPPORTED, f"the controller refused {text!r}: error:{code}")

