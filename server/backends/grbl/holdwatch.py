"""A hold must hold: a ``!`` the board did not take is sent again (pure; the controller writes).

The board may report before it acts on a ``!`` read with the poll after it, so a hold is
judged on the report to the second poll sent after it: still Run, and it is sent again, at most
:data:`RESENDS` times (a board that will not hold, grblHAL with its feed hold disabled, is said
once and left). Any other state ends the watch (Hold, and also Jog, Home, Idle: a hold there is
the board's to ignore), as do ``~`` and a reset. grblHAL's rig was seen to drop a ``!`` sent a
report after a resume, about one run in fifteen.
"""

from __future__ import annotations

from enum import Enum

RESENDS = 3


class Verdict(Enum):
    WAIT = "wait"
    RESEND = "resend"
    GIVE_UP = "give up"


class HoldWatch:
    """See the module docstring. Polls are counted by the controller: ``sent`` so far, and
    ``answered`` (the poll the report in hand answers)."""

    def __init__(self) -> None:
        self._asked_at: int | None = None  # polls sent when the '!' was
        self.resends = 0

    def asked(self, polls_sent: int, *, again: bool = False) -> None:
        """A ``!`` went to the board (``again``: a resend of the one watched)."""
        self._asked_at = polls_sent
        if not again:
            self.resends = 0

    def clear(self) -> None:
        """``~``, a reset, a lost connection: nothing to watch."""
        self._asked_at = None

    def report(self, state: str, polls_answered: int) -> Verdict:
        """The board's report, to poll number ``polls_answered``."""
        if self._asked_at is None:
            return Verdict.WAIT
        if state != "Run":
            self._asked_at = None
            return Verdict.WAIT
        if polls_answered < self._asked_at + 2:
            return Verdict.WAIT
        self.resends += 1
        if self.resends > RESENDS:
            self._asked_at = None
            return Verdict.GIVE_UP
        return Verdict.RESEND
