"""Accept errors ("Too many open files") logged once per burst, not once per attempt.

When the process runs out of descriptors, asyncio's listening sockets report every failed
``accept()`` to the loop's exception handler (with a traceback) and retry a second later, for
as long as the descriptors stay exhausted. :class:`AcceptErrorLog` wraps the loop's exception
handler: the first failure of a burst is logged in one line, the following ones are counted,
and one summary is logged once ``quiet_s`` pass without another. Every other loop error goes
to the handler that was there before.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

log = logging.getLogger("motiond.http")
ACCEPT_FAILED = "socket.accept() out of system resource"  # asyncio's message, selector loop
Context = dict[str, Any]


class AcceptErrorLog:
    """Install on a loop for as long as the listeners run; ``uninstall`` is repeatable."""

    def __init__(self, loop: asyncio.AbstractEventLoop, quiet_s: float = 5.0) -> None:
        self.loop = loop
        self.quiet_s = quiet_s
        self.repeats = 0
        self._previous = loop.get_exception_handler()
        self._burst_end: asyncio.TimerHandle | None = None
        self._installed = False

    def install(self) -> None:
        self._previous = self.loop.get_exception_handler()
        self.loop.set_exception_handler(self._handle)
        self._installed = True

    def uninstall(self) -> None:
        if not self._installed:
            return
        self._installed = False
        self.loop.set_exception_handler(self._previous)
        if self._burst_end is not None:
            self._burst_end.cancel()
            self._end_burst()

    def _handle(self, loop: asyncio.AbstractEventLoop, context: Context) -> None:
        if context.get("message") != ACCEPT_FAILED:
            if self._previous is not None:
                self._previous(loop, context)
            else:
                loop.default_exception_handler(context)
            return
        if self._burst_end is None:
            log.error("cannot accept connections: %s; further failures are counted until "
                      "%gs pass without one", context.get("exception"), self.quiet_s)
        else:
            self.repeats += 1
            self._burst_end.cancel()
        self._burst_end = loop.call_later(self.quiet_s, self._end_burst)

    def _end_burst(self) -> None:
        self._burst_end = None
        if self.repeats:
            log.warning("accepting connections failed %d more times before it recovered",
                        self.repeats)
        self.repeats = 0
