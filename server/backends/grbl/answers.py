"""The Grbl host's small pure parts: the realtime bytes that take an override to a value, what
reads as a board's answer, and the errors motiond answers for the board."""

from __future__ import annotations

import re
from collections.abc import Sequence

from server.errors import CommandError, Error
from server.protocol.events import Realtime

_OPTIONS = re.compile(r"^(\[OPT:[^,\]]*,\d+),\d+(.*)$")  # [OPT:flags,blocks,bytes...]
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


def overrides_bytes(feed: int | None, rapid: int | None, spindle: int | None) -> list[int]:
    """The realtime bytes that set the overrides given (None: left as it is): feed and spindle
    from 100 % by ±10s and ±1s, clamped to 10-200 %; rapid 100, 50, else 25 %."""
    data: list[int] = []
    for value, steps in ((feed, FEED_BYTES), (spindle, SPINDLE_BYTES)):
        if value is not None:
            data += override_bytes(max(10, min(200, value)), steps)
    if rapid is not None:
        data.append({100: Realtime.RAPID_100, 50: Realtime.RAPID_50}.get(rapid,
                                                                        Realtime.RAPID_25))
    return data


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



def front_buffer(messages: list[str], front_bytes: int) -> list[str]:
    """``$I``'s ``[OPT:V,15,128]``: the receive buffer a sender fills is the front's."""
    return [_OPTIONS.sub(lambda m: f"{m.group(1)},{front_bytes}{m.group(2)}", text)
            for text in messages]
