"""A playing job's runs of plain lines (:mod:`server.jobs.feeding`): the machine reads them with
numpy and appends them at once, and must plan exactly what the same lines sent one by one plan:
the same blocks (moves, speeds, follow actions of each S change), the same end state, the
tool's S; nothing read ahead of the planner; a stop ends a run as it ends a line."""

from __future__ import annotations

import asyncio
import random
from typing import Any

import pytest

from server.app import App
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import parse_line, parse_plain
from server.jobs import reading
from server.motion.moves import Action, Move
from tests.conftest import make_config
from tests.integration.test_babystep_in_job import recording as recording_targets
from tests.support.helpers import running


def raster_job(seed: int, lines: int = 1500) -> str:
    """A laser raster's lines: plain G1s with S changes (some on lines that do not move),
    a few G0s and F changes, and now and then a line that is not plain (a comment, M-codes,
    G91 for a while)."""
    rng = random.Random(seed)
    out = ["G21 G90 G94 M4 S0 F6000"]
    x = y = 10.0
    for index in range(lines):
        kind = rng.random()
        if kind < 0.02:
            out += rng.choice([["(a comment)"], ["M5"], ["M4"], ["G91", "G1 X0.5", "G90"]])
            continue
        x = round(min(max(x + rng.choice([0.1] * 20 + [-0.1, 0.25, 2.0]), 1.0), 90.0), 3)
        y = round(y + (0.1 if index % 200 == 0 else 0.0), 3)
        words = [rng.choice(["G1", "", "", "G0"]) if kind < 0.1 else "G1", f"X{x:g}"]
        if index % 200 == 0:
            words.append(f"Y{y:g}")
        if rng.random() < 0.2:
            words.append(f"S{rng.choice([0, 250, 800, 1000])}")
        if rng.random() < 0.01:
            words = [f"S{rng.choice([0, 500])}"]  # S alone: a follow action, no move
        if rng.random() < 0.01:
            words.append(f"F{rng.choice([3000, 6000])}")
        out.append(" ".join(word for word in words if word))
    return "\n".join(out) + "\n"


def recording(app: App) -> list[Any]:
    """Every block the step generator pops: its move's target, S and actions, its speeds."""
    planner, popped = app.kernel.machine.planner, []
    pop = planner.pop

    def pop_and_record():  # type: ignore[no-untyped-def]
        block = pop()
        if block is not None:
            move = block.move
            popped.append((None if move is None else (move.target_mm, move.s_value),
                           [(a.name, dict(a.params)) for a in block.actions],
                           block.entry_mm_s, block.cruise_mm_s, block.exit_mm_s))
        return block

    planner.pop = pop_and_record  # type: ignore[method-assign]
    return popped


async def played(text: str, runs: bool) -> tuple[list[Any], Any, int]:
    """The blocks, the end state and the lines the job ran as runs (0: one by one)."""
    async with running(make_config()) as app:
        kernel = app.kernel
        kernel.machine.feeds_runs = runs  # type: ignore[misc]
        read: list[int] = []
        begin_run = kernel.dispatcher.begin_run

        async def counting(*args):  # type: ignore[no-untyped-def]
            outcome = begin_run(*args)
            count = outcome if isinstance(outcome, int) else await outcome
            read.append(count)
            return count

        kernel.dispatcher.begin_run = counting  # type: ignore[method-assign]
        popped = recording(app)
        await kernel.jobs.save("raster.nc", text.encode())
        kernel.jobs.play("raster.nc")
        await kernel.jobs._task  # noqa: SLF001 - the player ends
        assert kernel.jobs.progress().state == "done"  # type: ignore[union-attr]
        interpreter = kernel.machine.interpreter
        end = (interpreter.position, repr(interpreter.save()), kernel.machine.tool.s,
               kernel.machine.stepgen.state.position_mm)
        return popped, end, sum(read)


async def test_a_job_in_runs_plans_the_blocks_of_its_lines_one_by_one(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    # one read of the file: on the virtual clock, motion goes on while a read waits for its
    # thread (real time), and may drain the planner there, in either mode
    monkeypatch.setattr(reading, "READ_LINES", 10_000)
    for seed in range(3):
        text = raster_job(seed)
        alone, end_alone, _ = await played(text, runs=False)
        together, end_together, in_runs = await played(text, runs=True)
        assert in_runs > 500, "a good share of the lines went in runs"
        assert any(actions for _, actions, *_ in together), "S changes rode the blocks"
        # the moves and actions exactly; the speeds to the last bits (where a block is
        # popped as the next is appended, or just before, rounds a junction's last bit
        # differently, one by one as in runs)
        assert [block[:2] for block in together] == [block[:2] for block in alone]
        assert [v for block in together for v in block[2:]] == pytest.approx(
            [v for block in alone for v in block[2:]], rel=1e-12, abs=1e-12)
        assert end_together[1:3] == end_alone[1:3]
        assert end_together[0] == end_alone[0]
        assert end_together[3] == pytest.approx(end_alone[3], abs=1e-9)


async def test_a_run_reads_no_further_than_the_planner_has_room_for() -> None:
    """A raster's short lines go in runs, each taking only what the planner has room for:
    nothing is read ahead of it, so a baby-step asked for mid-job lands right behind the
    moves already planned (within a run's room), not a batch's length later."""
    text = "G21 G90 G1 F6000\n" + "".join(
        f"G1 X{10 + (i % 400) * 0.1:.1f}\n" for i in range(2000))
    async with running(make_config()) as app:
        kernel = app.kernel
        taken = recording_targets(app)
        await kernel.jobs.save("raster.nc", text.encode())
        kernel.jobs.play("raster.nc")
        while kernel.machine.stepgen.state.blocks_done < 100:
            await app.clock.sleep(0.05)  # type: ignore[attr-defined]
        assert kernel.machine.line_s > 0.0, "runs were read"
        planned = len(taken)
        answer = kernel.jobs.interject("M290 Z0.05", kernel.status.ticket())
        assert answer is not None
        await answer
        step = next(i for i, target in enumerate(taken) if target[2] != 0.0)
        assert planned <= step <= planned + 64, (planned, step)
        kernel.jobs.abort()
        await asyncio.gather(kernel.jobs._task, return_exceptions=True)  # noqa: SLF001


def test_a_runs_outputs_are_moves_and_the_actions_of_lines_that_only_change_s() -> None:
    made = Interpreter(InterpreterSettings(("X", "Y"), (-1e3,) * 2, (1e3,) * 2))
    made.execute(parse_line("G1 F600 M3"))
    lines = ["G1 X1 S10", "S20", "X2", "X2 S30", "X3 S30"]
    run = made.execute_plain(parse_plain(lines).columns, 0, len(lines))
    outputs = run.outputs()
    assert [type(out) for out in outputs.outputs] == [Move, Action, Move, Action, Move]
    assert [a.params["s"] for out in outputs.outputs
            for a in ([out] if isinstance(out, Action) else out.actions)] == [10.0, 20.0, 30.0]
    assert outputs.actions_at == [1, 3]
    assert [out.s_value for out in outputs.outputs if isinstance(out, Move)] == [10.0, 20.0, 30.0]
