"""The one way G-code reaches the planner, live and offline alike."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from server.motion.block import FloatArray
from server.motion.moves import Action, Move, Output, Sync
from server.motion.planner import Planner


def offer(planner: Planner, outputs: Sequence[Output], start: int = 0) -> int:
    """Append ``outputs[start:]`` (a line's moves and ordered actions) to ``planner`` in order,
    until the planner is full or a :class:`Sync` comes; return the index of the first output
    not taken. The live machine waits for room (or carries the Sync out) and offers the rest;
    ``estimate`` and ``render`` pop planned blocks and offer the rest, so both plan the same
    block sequence."""
    full = planner.is_full()
    for index in range(start, len(outputs)):
        output = outputs[index]
        if full or type(output) is Sync:
            return index
        if type(output) is Move:
            full = planner.append(output)  # (which says whether the planner is full now)
        else:
            planner.append_action(output)  # type: ignore[arg-type]
            full = planner.is_full()
    return len(outputs)


@dataclass(slots=True)
class MoveRun:
    """The outputs of a run of plain lines (:mod:`server.gcode.plain`), in order: each line's
    move (carrying the line's follow action when it changed S, as the one-line path gives it)
    or, for a line that changed S without moving, that action alone. ``ends``, ``feeds_mm_s``
    and ``rapid`` have a row per output (an action's row is never read); ``actions_at`` lists
    where the actions stand (few: a run is nearly all moves)."""

    outputs: list[Move | Action]
    ends: FloatArray
    feeds_mm_s: FloatArray
    rapid: npt.NDArray[np.bool_]
    actions_at: list[int]


def offer_run(planner: Planner, run: MoveRun, start: int = 0) -> int:
    """:func:`offer` of ``run.outputs[start:]``, its stretches of moves appended at once
    (:meth:`~server.motion.planner.Planner.append_run`: the very blocks appending them one by
    one gives); the index of the first output not taken (the planner is full)."""
    outputs, actions_at, count = run.outputs, run.actions_at, len(run.outputs)
    index = start
    while index < count and not planner.is_full():
        output = outputs[index]
        if type(output) is not Move:
            planner.append_action(output)  # type: ignore[arg-type]
            index += 1
            continue
        after = bisect_right(actions_at, index)
        stop = actions_at[after] if after < len(actions_at) else count
        taken = planner.append_run(outputs[index:stop], run.ends[index:stop],  # type: ignore[arg-type]
                                   run.feeds_mm_s[index:stop], run.rapid[index:stop])
        index += taken
        if index < stop:
            break  # full
    return index
