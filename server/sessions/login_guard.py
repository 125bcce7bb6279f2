"""Tokens on the line protocol: constant-time comparison, and wrong guesses slowed and summarised.

A wrong ``$AUTH`` token is answered after a delay that doubles with every failure of the same
client address in its current burst (``[protocol] auth_delay_s``, then 2x, 4x... up to
``auth_max_delay_s``); a burst ends after :data:`BURST_QUIET_S` without a failure. Lines of one
connection run one at a time, so the delay also holds back that connection's next guess; the
session closes a connection after ``auth_failures_per_connection`` wrong tokens.

The log gets one line when a burst begins and then one summary line (with the count) per
:data:`SUMMARY_S` while failures go on, never one line per guess. At most :data:`MAX_ADDRESSES`
addresses are remembered; the one quiet for longest is forgotten first.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger("motiond.auth")
BURST_QUIET_S = 600.0
SUMMARY_S = 60.0
MAX_ADDRESSES = 1024
MAX_DOUBLINGS = 30


def token_matches(given: str | None, expected: str) -> bool:
    """Whether ``given`` is the token, in time independent of both values.

    Both sides are hashed to bytes first: ``hmac.compare_digest`` refuses non-ASCII ``str``
    (TypeError) and takes time that depends on the lengths.
    """
    if given is None:
        return False
    return hmac.compare_digest(_digest(given), _digest(expected))


def _digest(text: str) -> bytes:
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).digest()


@dataclass(slots=True)
class _Burst:
    failures: int
    unlogged: int
    last_s: float


class LoginGuard:
    """Failed logins per client address, bounded in size. See the module docstring."""

    def __init__(
        self,
        delay_s: float,
        max_delay_s: float,
        *,
        now_s: Callable[[], float] = time.monotonic,
        max_addresses: int = MAX_ADDRESSES,
    ) -> None:
        self.delay_s = delay_s
        self.max_delay_s = max_delay_s
        self._now_s = now_s
        self._max_addresses = max_addresses
        self._bursts: OrderedDict[str, _Burst] = OrderedDict()
        self._timer: asyncio.TimerHandle | None = None

    def __len__(self) -> int:
        return len(self._bursts)

    def failed(self, address: str, who: str) -> float:
        """Record a wrong token from ``address``; returns how long to wait before answering."""
        now_s = self._now_s()
        burst = self._bursts.pop(address, None)
        if burst is None or now_s - burst.last_s > BURST_QUIET_S:
            if burst is not None:
                self._summarise(address, burst)
            burst = _Burst(0, 0, now_s)
            log.warning("%s: wrong token from %s (further failures from this address are "
                        "counted and summarised every %.0f s)", who, address, SUMMARY_S)
        else:
            burst.unlogged += 1
        burst.failures += 1
        burst.last_s = now_s
        self._bursts[address] = burst
        while len(self._bursts) > self._max_addresses:
            self._summarise(*self._bursts.popitem(last=False))
        self._start_timer()
        doublings = min(burst.failures - 1, MAX_DOUBLINGS)
        return min(self.max_delay_s, self.delay_s * float(1 << doublings))

    def succeeded(self, address: str) -> None:
        """The right token: the address's burst ends."""
        burst = self._bursts.pop(address, None)
        if burst is not None:
            self._summarise(address, burst)

    def summarise(self) -> None:
        """Log the failures not yet logged; forget addresses quiet for a whole burst period."""
        now_s = self._now_s()
        for address, burst in list(self._bursts.items()):
            self._summarise(address, burst)
            if now_s - burst.last_s > BURST_QUIET_S:
                del self._bursts[address]

    def close(self) -> None:
        """Log what is left; stop the timer. Repeatable."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self.summarise()

    def _summarise(self, address: str, burst: _Burst) -> None:
        if burst.unlogged:
            log.warning("%d more wrong tokens from %s (%d in this burst)",
                        burst.unlogged, address, burst.failures)
            burst.unlogged = 0

    def _start_timer(self) -> None:
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(SUMMARY_S, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        self.summarise()
        if self._bursts:
            self._start_timer()
