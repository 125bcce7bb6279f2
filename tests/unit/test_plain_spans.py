"""A live job's spans of plain lines (:class:`server.gcode.plain.PlainSpan`): a run's outputs
are the one-line path's, follow actions and all, each tagged with its line; the state after
any number of a run's lines (where a span the planner had no room for whole leaves the
interpreter) is the state the one-line path reaches there; and the shared reading of a chunk
(:func:`plain_items`) gives a span again until what the interpreter takes of it is read."""

from __future__ import annotations

import contextlib
import random

import pytest

from server.errors import CommandError
from server.gcode import plain
from server.gcode.interpreter import Interpreter
from server.gcode.parser import parse_line
from server.gcode.plain import PlainRun, PlainSpan, plain_items
from server.motion.moves import Move, Output
from tests.unit.test_plain_lines import LIMIT_BYTES, interpreter, random_job

AXES = ("X", "Y", "Z")


def state(made: Interpreter) -> tuple[object, ...]:
    """What a run's rewind sets, as the one-line path leaves it."""
    modal = made.save()[0]
    return made.position, modal.motion, modal.feed, modal.s


def runs_of(lines: list[str], made: Interpreter) -> list[tuple[int, PlainRun]]:
    """Every run the reading of ``lines`` takes (its first line's index and the run), each
    line that is not in one read alone (a refused one changes nothing)."""
    runs: list[tuple[int, PlainRun]] = []
    for item in plain_items(lines, AXES, LIMIT_BYTES, made.takes_runs):
        if isinstance(item, PlainSpan):
            run = made.execute_plain(item.columns, item.start, item.stop)
            item.taken = item.count = run.count
            if run.count:
                runs.append((item.start, run))
            continue
        replay([lines[item]], made)
    return runs


@pytest.mark.parametrize("seed", range(8))
def test_a_runs_outputs_are_each_lines_outputs_actions_and_all(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(plain, "MIN_RUN", 2 + seed % 5)
    lines = ["G21 G90 G94 M3 S0 F1000", *random_job(seed, 800)]
    runs = runs_of(lines, interpreter())
    assert sum(run.count for _, run in runs) > 100, "runs were read"
    checked = 0
    for first, run in runs:
        before = interpreter()
        replay(lines[:first], before)
        outputs, from_lines = run.outputs()
        expected: list[Output] = []
        owners: list[int] = []
        for offset in range(run.count):
            made = before.execute(parse_line(lines[first + offset]))
            expected += made
            owners += [offset] * len(made)
        assert repr(outputs) == repr(expected)  # (repr: -0.0 is not 0.0)
        assert from_lines == owners, "each output's line"
        assert all(len(made) <= 1 for made in split(expected, owners)), "a line, an output"
        checked += sum(isinstance(out, Move) and bool(out.actions) for out in outputs)
    assert checked > 20, "moves carrying a new S were compared"


@pytest.mark.parametrize("seed", range(4))
def test_the_state_after_any_number_of_a_runs_lines_is_the_one_line_paths(seed: int) -> None:
    lines = ["G21 G90 G94 M4 S0 F600", *random_job(100 + seed, 600)]
    rng = random.Random(seed)
    runs = runs_of(lines, interpreter())
    assert runs
    for first, run in runs:
        made = interpreter()
        replay(lines[:first], made)
        for taken in sorted({0, run.count, *rng.sample(range(run.count + 1), 3)}):
            alone = interpreter()
            replay(lines[:first + taken], alone)
            assert repr(run.after(taken)) == repr(state(alone)), (first, taken)
            made.rewind(run, taken)  # (from wherever it was: the state is set, not stepped)
            assert repr(made.runs_state()) == repr(alone.runs_state())


def test_a_span_is_given_again_until_the_interpreter_has_read_what_it_takes() -> None:
    lines = ["G1 F600 X1", *[f"X{i} S{i % 2}" for i in range(2, 80)], "G2 X1 Y1 I1", "X5"]
    made = interpreter()
    given: list[tuple[int, int]] = []
    alone: list[int] = []
    for item in plain_items(lines, AXES, LIMIT_BYTES, made.takes_runs):
        if isinstance(item, PlainSpan):
            given.append((item.start, item.taken))
            item.count = item.stop - item.start  # the interpreter takes it all ...
            item.taken = min(item.count, item.taken + 30)  # ... and the planner 30 a time
        else:
            alone.append(item)
    assert given == [(0, 0), (0, 30), (0, 60)], "the same span, read on from where it was"
    assert alone == [79, 80], "the lines after the span, one by one"


def test_a_span_the_interpreter_takes_none_of_is_read_line_by_line() -> None:
    lines = [f"G1 X{i}" for i in range(1, 50)]
    items = list(plain_items(lines, AXES, LIMIT_BYTES, lambda: True))  # (taken stays 0)
    assert isinstance(items[0], PlainSpan) and items[1:] == list(range(49))


def replay(lines: list[str], made: Interpreter) -> None:
    """The one-line path through ``lines``; a line it refuses changes nothing."""
    for text in lines:
        with contextlib.suppress(CommandError):
            made.execute(parse_line(text))


def split(outputs: list[Output], owners: list[int]) -> list[list[Output]]:
    by_line: dict[int, list[Output]] = {}
    for output, line in zip(outputs, owners, strict=True):
        by_line.setdefault(line, []).append(output)
    return list(by_line.values())
