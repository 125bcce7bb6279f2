"""What a controller prints on its own, made safe for motiond's clients: a pure core.

A board's unsolicited lines (``[MSG:...]``, ``[GC:...]`` after a ``$G``, noise) are pushed to
every client. A chatty or noisy board must not flood them (a slow reader would be
disconnected) nor the log: :class:`FeedbackGate` lets through at most ``rate_per_s`` lines a
second (bursts of ``burst``) and replaces the rest by one summary line with their count.
:func:`clean_line` keeps a line within printable ASCII and a bounded length, and wraps anything
that could read as a reply, or as a report a sender must only see on request, in
``[MSG:controller: ...]``.
"""

from __future__ import annotations

from server.runtime.ratelimit import TokenBucket

MAX_TEXT = 200  # characters kept of one controller line
PASSED_AS_IS = ("[MSG:", "[GC:", "[PRB:", "[echo:")
DEFAULT_RATE_PER_S = 20.0
DEFAULT_BURST = 40.0


def clean_line(text: str) -> str:
    """``text`` as a line safe to push: printable ASCII, bounded, never read as ``ok``."""
    printable = "".join(c for c in text if c.isascii() and c.isprintable())[:MAX_TEXT]
    inner = printable[1:-1] if printable.startswith("[") and printable.endswith("]") else ""
    one_field = bool(inner) and "[" not in inner and "]" not in inner
    if one_field and printable.startswith(PASSED_AS_IS) and (
            printable.startswith("[MSG:") or "ok" not in printable):
        return printable
    bare = printable.replace("[", "(").replace("]", ")")
    return f"[MSG:controller: {bare}]"


def clean_reply(text: str) -> str:
    """A line printed before an answer (``$$`` output, ``[G54:...]``) for the sender."""
    printable = "".join(c for c in text if c.isascii() and c.isprintable())[:MAX_TEXT]
    if printable.lower().startswith("ok") or not printable:
        return clean_line(text)
    return printable


class FeedbackGate:
    """Rate limit with a count of what was held back; times are any monotonic seconds."""

    def __init__(self, now_s: float, rate_per_s: float = DEFAULT_RATE_PER_S,
                 burst: float = DEFAULT_BURST) -> None:
        self._bucket = TokenBucket(rate_per_s, burst, now_s)
        self.held_back = 0  # lines not shown since the last summary
        self.total_held_back = 0

    def offer(self, text: str, now_s: float) -> list[str]:
        """The lines to push now for one controller line (none while over the rate)."""
        if self._bucket.take(now_s) > 0:
            self.held_back += 1
            self.total_held_back += 1
            return []
        return [*self.flush(now_s, taken=True), clean_line(text)]

    def offer_lines(self, texts: list[str], now_s: float) -> list[str]:
        """:meth:`offer` for lines read at once: once over the rate, the rest of them are
        counted in one step (a chatty board sends thousands a second)."""
        shown: list[str] = []
        for index, text in enumerate(texts):
            lines = self.offer(text, now_s)
            if not lines:  # no time passes within the batch: the rest are held back too
                rest = len(texts) - index - 1
                self.held_back += rest
                self.total_held_back += rest
                break
            shown += lines
        return shown

    def flush(self, now_s: float, *, taken: bool = False) -> list[str]:
        """The summary of what was held back, if any and if the rate allows it now."""
        if not self.held_back or (not taken and self._bucket.take(now_s) > 0):
            return []
        count, self.held_back = self.held_back, 0
        return [f"[MSG:controller: {count} more lines not shown (too many)]"]
