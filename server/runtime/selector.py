"""asyncio's event loop with timers to the microsecond, not the millisecond.

asyncio's default selector on Linux is epoll, and ``epoll_wait`` takes whole milliseconds:
Python rounds every wait up (``math.ceil(timeout * 1e3)``), so a timer due in 0.05 ms is
served after 1 ms. A loop ticking at 1 kHz almost always waits less than a millisecond, so
that rounding alone made the step generator's tick and every timer up to a millisecond late,
on top of the loop's own work (the streaming benchmark's stall: about 1.2 ms).

:class:`FineEpollSelector` waits on the epoll descriptor itself with ``select()``, whose
timeout is in microseconds, then collects the ready events with a zero-timeout ``epoll_wait``
(only when ``select()`` saw some: a timer's wake-up makes one system call, not two):
epoll still watches every descriptor (no ``FD_SETSIZE`` limit on connections); ``select()``
only ever sees the one epoll descriptor. Should that descriptor be numbered beyond what
``select()`` takes, it falls back to epoll's own millisecond waits.
"""

from __future__ import annotations

import asyncio
import select
import selectors

FD_SETSIZE = 1024  # select() takes descriptors below this


class FineEpollSelector(selectors.EpollSelector):
    """An epoll selector whose waits end to the microsecond; see the module docstring."""

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        epoll_fd = self.fileno()
        if timeout is not None and timeout > 0.0 and epoll_fd < FD_SETSIZE:
            ready, _, _ = select.select([epoll_fd], [], [], timeout)  # an event or the time
            if not ready:  # a timer's time came with nothing ready: no epoll_wait to ask
                return []
            timeout = 0.0
        return super().select(timeout)


def asyncio_loop() -> asyncio.AbstractEventLoop:
    """A new asyncio event loop on :class:`FineEpollSelector` (``motiond serve``'s default
    when uvloop is not installed)."""
    return asyncio.SelectorEventLoop(FineEpollSelector())
