"""Where the tool was at any instant: the pieces steps were generated from (pure).

The MCU executes the step schedule a lead time behind the step generator, so what it has done
at host time ``t`` is the trajectory at print time ``t - lead``. The backend keeps the pieces it
generated steps from (the one being generated included, cut where a feed hold or a stop cut it)
for ``keep_s`` and evaluates the one covering the asked time exactly, however seldom the step
generator ticks.
"""

from __future__ import annotations

import bisect
from collections import deque

from server.motion.backend import Piece

EPSILON_S = 1e-9  # a piece that ends this close to a cut is not cut (rounding)


class Trail:
    """The recent pieces in time order; see the module docstring."""

    def __init__(self, keep_s: float) -> None:
        self.keep_s = keep_s
        self._pieces: deque[Piece] = deque()

    def __len__(self) -> int:
        return len(self._pieces)

    def add(self, piece: Piece) -> None:
        pieces = self._pieces
        pieces.append(piece)
        oldest_s = piece.start_s - self.keep_s
        while len(pieces) > 1 and pieces[1].start_s < oldest_s:
            pieces.popleft()

    def cut(self, at_s: float) -> None:
        """Motion after ``at_s`` was replaced (a hold, a stop): the trail ends there."""
        pieces = self._pieces
        while pieces and pieces[-1].start_s >= at_s and len(pieces) > 1:
            pieces.pop()
        if pieces and pieces[-1].start_s + pieces[-1].duration_s > at_s + EPSILON_S:
            last = pieces.pop()
            pieces.append(last.lasting(max(0.0, at_s - last.start_s)))

    def clear(self) -> None:
        self._pieces.clear()

    def position_at(self, at_s: float) -> tuple[float, ...] | None:
        """The position at print time ``at_s`` (before the first piece: its start; after the
        last: its end); None when there is no piece."""
        found = self._at(at_s)
        if found is None:
            return None
        piece, t = found
        distance = piece.start_mm_s * t + 0.5 * piece.accel_mm_s2 * t * t
        return tuple(p + u * distance for p, u in zip(piece.start_mm, piece.unit, strict=True))

    def speed_at(self, at_s: float) -> float:
        """The path speed at print time ``at_s`` (0 outside the pieces: at rest)."""
        found = self._at(at_s)
        if found is None or not 0.0 < at_s - found[0].start_s < found[0].duration_s:
            return 0.0
        piece, t = found
        return piece.start_mm_s + piece.accel_mm_s2 * t

    def _at(self, at_s: float) -> tuple[Piece, float] | None:
        """The piece covering ``at_s`` (or the nearest) and the time into it, clamped."""
        pieces = self._pieces
        if not pieces:
            return None
        index = bisect.bisect_right(pieces, at_s, key=lambda piece: piece.start_s) - 1
        piece = pieces[max(index, 0)]
        return piece, min(max(at_s - piece.start_s, 0.0), piece.duration_s)
