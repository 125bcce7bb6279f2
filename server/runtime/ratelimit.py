"""A token bucket: at most ``rate_per_s`` events per second on average, bursts of ``burst``;
and the input budgets of the line protocol's connections, each one's and all of theirs
together (the kernel holds the shared ones, each session its own)."""

from __future__ import annotations

import time

BURST_BYTES = 1024  # what a connection that may not control may send at once (then its rate)
TOTAL_BURST_BYTES = 2048  # what all of them may send at once
REALTIME_BURST_BYTES = 256  # realtime bytes one connection may send at once (then at its rate)
REALTIME_TOTAL_BURST_BYTES = 512  # what all flooding connections may send at once


class TokenBucket:
    """Times are seconds on any monotonic clock, passed in by the caller (no clock inside)."""

    def __init__(self, rate_per_s: float, burst: float, now_s: float) -> None:
        if rate_per_s <= 0 or burst < 1:
            raise ValueError("a token bucket needs rate_per_s > 0 and burst >= 1")
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._tokens = burst
        self._last_s = now_s

    def take(self, now_s: float, amount: float = 1.0) -> float:
        """Take ``amount`` tokens (at most ``burst``): 0.0 if they were free, else the seconds
        until they will be (none taken)."""
        wait_s = self.wait_s(now_s, amount)
        if wait_s == 0.0:
            self._tokens -= min(amount, self.burst)
        return wait_s

    def wait_s(self, now_s: float, amount: float = 1.0) -> float:
        """The seconds until ``amount`` tokens (at most ``burst``) are free; none taken."""
        elapsed_s = max(0.0, now_s - self._last_s)
        self._tokens = min(self.burst, self._tokens + elapsed_s * self.rate_per_s)
        self._last_s = now_s
        missing = min(amount, self.burst) - self._tokens
        return 0.0 if missing <= 0 else missing / self.rate_per_s


class Allowance:
    """Paid after the fact: ``spend`` may take it below zero (a slice already examined costs
    what it cost); :meth:`wait_s` says how long until it is above zero again. Refills at
    ``rate_per_s`` up to ``burst``. Times are seconds on any monotonic clock, passed in."""

    def __init__(self, rate_per_s: float, burst: float, now_s: float) -> None:
        if rate_per_s <= 0 or burst <= 0:
            raise ValueError("an allowance needs rate_per_s > 0 and burst > 0")
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._level = burst
        self._last_s = now_s

    def level(self, now_s: float) -> float:
        """What is left (negative: overspent)."""
        elapsed_s = max(0.0, now_s - self._last_s)
        self._level = min(self.burst, self._level + elapsed_s * self.rate_per_s)
        self._last_s = now_s
        return self._level

    def spend(self, now_s: float, amount: float) -> None:
        self._level = self.level(now_s) - amount

    def wait_s(self, now_s: float) -> float:
        """Seconds until something is left again (0.0: now)."""
        level = self.level(now_s)
        return 0.0 if level > 0 else (1.0 - level) / self.rate_per_s


def input_budget(rate_bytes_per_s: float, burst_bytes: float = BURST_BYTES) -> TokenBucket:
    """A budget of input bytes for connections that may not control (see
    ``LineAdmission.pace_input``)."""
    return TokenBucket(rate_bytes_per_s, burst_bytes, time.monotonic())


def realtime_allowance(rate_bytes_per_s: float, burst_bytes: float) -> Allowance:
    """A budget of realtime bytes (see ``LineAdmission.feed``)."""
    return Allowance(rate_bytes_per_s, burst_bytes, time.monotonic())
