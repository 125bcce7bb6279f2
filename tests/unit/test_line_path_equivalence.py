"""The line path's shortcuts change nothing: each corpus file gives the same planned blocks (every
speed, junction, duration and action) through the live path (the parser's and the interpreter's
fast paths, :func:`~server.motion.feed.offer`) as through the general parser, the general
interpreter and one ``append`` per output; and any G1 line a sender may write parses the same
either way.

The general path is the reference: nothing here is a hard-coded number.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.errors import CommandError
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import Line, _parse_framed_or_commented, parse_line
from server.motion.block import Block
from server.motion.feed import offer
from server.motion.moves import Move, Output, Sync
from server.motion.planner import Planner, PlannerSettings
from tests.conftest import CORPUS
from tests.unit.test_corpus_interpreter import claimed_by_a_module

MACHINE = InterpreterSettings(("X", "Y", "Z"), (-1000.0,) * 3, (1000.0,) * 3, soft_limits=True)
# a small window, so that blocks are popped (and planned) while lines still come
LIMITS = PlannerSettings((300.0, 300.0, 20.0), (2000.0, 2000.0, 200.0), junction_deviation_mm=0.02,
                         max_blocks=48, max_planned_s=0.25, plan_blocks=24, sync_blocks=8)
MOST_LINES = 12_000  # of each file (the raster is 54,000 lines of the same kind)


class GeneralOnly(Interpreter):
    """The interpreter with its fast path switched off."""

    def _fast_line(self, line: Line) -> list[Output] | None:
        return None


def live_blocks(lines: list[str]) -> tuple[list[Block], int | None]:
    """The blocks as the machine plans them: fast parser and interpreter, ``offer``, a block
    popped whenever the planner is full; and the first refused line's error code."""
    interpreter, planner = Interpreter(MACHINE), Planner(LIMITS, (0.0, 0.0, 0.0))
    blocks: list[Block] = []
    for text in lines:
        line = parse_line(text)
        if claimed_by_a_module(line):
            continue
        try:
            outputs = interpreter.execute(line)
        except CommandError as error:
            return drained(planner, blocks), error.code
        index = offer(planner, outputs)
        while index < len(outputs):
            if type(outputs[index]) is Sync:
                index += 1
            else:
                blocks.append(popped(planner))
            index = offer(planner, outputs, index)
    return drained(planner, blocks), None


def general_blocks(lines: list[str]) -> tuple[list[Block], int | None]:
    """The same, through the general parser and interpreter, one output at a time."""
    interpreter, planner = GeneralOnly(MACHINE), Planner(LIMITS, (0.0, 0.0, 0.0))
    blocks: list[Block] = []
    for text in lines:
        line = _parse_framed_or_commented(text)
        if claimed_by_a_module(line):
            continue
        try:
            outputs = interpreter.execute(line)
        except CommandError as error:
            return drained(planner, blocks), error.code
        for output in outputs:
            if type(output) is Sync:
                continue
            while planner.is_full():
                blocks.append(popped(planner))
            if type(output) is Move:
                planner.append(output)
            else:
                planner.append_action(output)  # type: ignore[arg-type]
    return drained(planner, blocks), None


def popped(planner: Planner) -> Block:
    block = planner.pop()
    assert block is not None
    return block


def drained(planner: Planner, blocks: list[Block]) -> list[Block]:
    while (block := planner.pop()) is not None:
        blocks.append(block)
    return blocks


@pytest.mark.parametrize("name", sorted(path.name for path in Path(CORPUS).iterdir()
                                        if path.suffix in (".nc", ".gcode")))
def test_a_corpus_file_plans_the_same_blocks_through_the_fast_paths_as_the_general_ones(
        name: str) -> None:
    lines = Path(CORPUS, name).read_text(encoding="utf-8").splitlines()[:MOST_LINES]
    live, reference = live_blocks(lines), general_blocks(lines)
    assert live[1] == reference[1]
    assert len(live[0]) == len(reference[0])
    assert live[0] or live[1] is not None  # (a file refused before its first move: no block)
    for number, (ours, theirs) in enumerate(zip(live[0], reference[0], strict=True)):
        assert ours == theirs, f"block {number} differs"


# -- G1 lines as senders write them ----------------------------------------------------------
NUMBER = st.one_of(
    st.floats(-2e9, 2e9, allow_nan=False).map(lambda v: f"{v:.{abs(hash(v)) % 5}f}"),
    st.integers(-99999, 99999).map(str),
    st.from_regex(r"[-+]?(\d{1,4}\.?\d{0,4}|\.\d{1,4})", fullmatch=True),
)
LETTER = st.sampled_from("XYZFSxyzfsGgNnMT")
SPACE = st.sampled_from(["", " ", "  ", "\t"])


@st.composite
def g1_lines(draw: st.DrawFn) -> str:
    """``G1`` and axis, F and S words in the spellings senders use (case, spacing, leading
    zeros, signs, line numbers), and now and then a word the fast path must leave alone."""
    words = [draw(st.sampled_from(["G1", "g1", "G01", "G0", "", "N12 G1"]))]
    for _ in range(draw(st.integers(0, 5))):
        words.append(draw(LETTER) + draw(SPACE) + draw(NUMBER))
    tail = draw(st.sampled_from(["", "", "", " ;laser", " (move)", "*57", " %", "X", "E1"]))
    return draw(SPACE).join(words) + tail


@settings(max_examples=400, deadline=None)
@given(g1_lines())
def test_a_g1_line_parses_the_same_on_the_fast_path_as_on_the_general_one(text: str) -> None:
    fast, general = parse_line(text), _parse_framed_or_commented(text)
    assert (fast.error and fast.error.code) == (general.error and general.error.code)
    assert (fast.letters, fast.values, fast.line_number, fast.comments, fast.block_delete) == (
        general.letters, general.values, general.line_number, general.comments,
        general.block_delete)
