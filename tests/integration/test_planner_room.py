"""Back-pressure in batches: a writer held by a full planner is let in once a sixteenth of the
window has drained, not at every popped block (see ``Planner.has_room``)."""

from __future__ import annotations

from server.motion.moves import Move
from tests.conftest import make_config
from tests.support.helpers import running, submit_all


async def test_a_full_planner_takes_the_next_lines_in_batches_of_a_sixteenth() -> None:
    config = make_config(planner={"max_blocks": 32, "max_planned_s": 60.0})
    async with running(config) as app:
        planner = app.kernel.machine.planner
        counts: list[int] = []  # the window's blocks after each append
        append = planner.append

        def counted(move: Move) -> bool:
            full = append(move)
            counts.append(len(planner))
            return full

        planner.append = counted  # type: ignore[method-assign]
        # 1 mm moves at 10 mm/s: each takes about 0.1 s, so a tick pops at most one
        lines = ["G1 F600"] + [f"G1 X{k}" for k in range(1, 49)]
        await submit_all(app, lines)
        await app.kernel.machine.wait_idle()
    assert counts[:32] == list(range(1, 33))
    # from the moment it was full, the window lets lines in two at a time (32 / 16 blocks)
    assert counts[32:] == [31, 32] * 8
    assert app.kernel.machine.stepgen.state.position_mm[0] == 48.0
