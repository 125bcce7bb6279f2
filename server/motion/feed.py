"""The one way G-code reaches the planner, live and offline alike."""

from __future__ import annotations

from collections.abc import Sequence

from server.motion.moves import Move, Output, Sync
from server.motion.planner import Planner


def offer(planner: Planner, outputs: Sequence[Output], start: int = 0,
          stop: int | None = None) -> int:
    """Append ``outputs[start:stop]`` (a line's moves and ordered actions) to ``planner`` in
    order, until the planner is full or a :class:`Sync` comes; return the index of the first
    output not taken. The live machine waits for room (or carries the Sync out) and offers the
    rest; ``estimate`` and ``render`` pop planned blocks and offer the rest, so both plan the
    same block sequence."""
    full = planner.is_full()
    stop = len(outputs) if stop is None else stop
    for index in range(start, stop):
        output = outputs[index]
        if full or type(output) is Sync:
            return index
        if type(output) is Move:
            full = planner.append(output)  # (which says whether the planner is full now)
        else:
            planner.append_action(output)  # type: ignore[arg-type]
            full = planner.is_full()
    return stop
