"""A job's plan reads its plain lines in runs (:mod:`server.gcode.plain`): the batch parse
(:func:`parse_plain`) and interpretation (:meth:`Interpreter.execute_plain`) agree with the
one-line path (:func:`parse_line`, :meth:`Interpreter.execute`) on every line of the corpus
and of random jobs made to hit their edges, and the plan (extent, time) is the one-line
path's to the bit."""

from __future__ import annotations

import io
import math
import random
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from server.config import CoreConfig
from server.errors import CommandError
from server.gcode import parser, plain
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import parse_line, parse_plain
from server.gcode.plain import PlainRun, lines_read
from server.machine.parts import interpreter_settings
from server.motion.moves import Action, ActionName, Move, Output
from server.offline import estimate as offline
from server.offline.estimate import estimate, extent, file_chunks
from tests.conftest import CORPUS, make_config

LIMIT_BYTES = 256
MOTIONS = ["G0", "G1", "G00", "G01", "G1.0", "g1", "G0.0"]
ACCEPTED = [  # lines the interpreter takes (most of them not plain)
    "G90", "G91", "G20", "G21", "G94", "M3 S100", "M4", "M5", "G4 P0.01", "G92 X0", "G92.1",
    "G54", "G55", "G10 L20 P2 X5", "", "  ", "%", "/G1 X5", "N10 G1 X3", "G1 X5 (a comment)",
    "G1 X5 ; a comment", "G1\tX5", "X-0", "Y-0 S-0", "G1 X 1 2.5", "G1X5Y6", "S1 Y.5 x-1",
]
REFUSED = [  # lines the parser or the interpreter refuses
    "G1 F0 X5", "F-5", "S-1", "G1 X1" + "0" * 400, "X1 X2", "G0 G1 X5", "G1 X2e3", "X1.2.3",
    "X+", "X.", "G1 X", "G1 X5 é", "G1 X1_0", "G1 X5 Q1", "G1 X5*99", "X" + "9" * 10,
]


def number(rng: random.Random, low: float = -400.0) -> str:
    value = rng.choice([0.0, -0.0, 1.0, 0.1 * rng.randrange(int(10 * low), 3000),
                        rng.uniform(low, 400), 5e-7 * rng.randrange(3)])
    return rng.choice([f"{value:.3f}", f"{value:.7f}", f"{value:.1f}", f"{value:.0f}"])


def random_job(seed: int, count: int) -> list[str]:
    """Mostly plain lines (a G0/G1 or none, axis words, F, S, in any order), and every 12th
    line or so one the interpreter takes that changes its state."""
    rng = random.Random(seed)
    lines = []
    for _ in range(count):
        if rng.random() < 0.08:
            lines.append(rng.choice(ACCEPTED))
            continue
        words = [rng.choice(MOTIONS)] if rng.random() < 0.4 else []
        words += [letter + number(rng) for letter in rng.sample("XYZxyz"[rng.randrange(2)::2],
                                                                rng.randrange(0, 4))]
        words += [f"F{rng.choice(['600', '1000.5', '6000', '+300', '.5'])}"] \
            if rng.random() < 0.1 else []
        words += [f"S{number(rng, 0.0)}"] if rng.random() < 0.5 else []
        rng.shuffle(words)
        lines.append(rng.choice([" ", "", "  "]).join(words) or "G1")
    return lines


def corpus_lines() -> list[str]:
    return [line for path in sorted(Path(CORPUS).iterdir()) if path.suffix != ".md"
            for line in path.read_text(errors="replace").splitlines()]


def bits(value: float) -> str:
    return value.hex()


@pytest.mark.parametrize("source", ["corpus", "random"])
def test_a_line_is_plain_only_as_parse_line_reads_it_and_then_the_words_agree(
    source: str,
) -> None:
    lines = corpus_lines() if source == "corpus" else (
        random_job(1, 3000) + REFUSED + ["G1 X+.5 Y-.5", "X1" + "0" * 8, "X1" + "0" * 9])
    parsed = parse_plain(lines)
    assert parsed.plain.sum() > len(lines) // 2, "most lines are plain"
    for index, text in enumerate(lines):
        line = parse_line(text)
        taken = line.error is None and line.line_number is None and not line.comments \
            and line.checksum is None and not line.block_delete and line.letters != "" \
            and len(set(line.letters)) == len(line.letters) and "\t" not in text \
            and text.isascii()
        assert bool(parsed.plain[index]) == taken, text
        if taken:
            words = {letter: bits(value) for letter, value in line.words}
            batch = {letter: bits(float(column[index]))
                     for letter, column in parsed.columns.items()
                     if not math.isnan(column[index])}
            assert batch == words, text


def test_a_chunk_with_a_line_ending_inside_a_line_is_left_to_the_one_line_path() -> None:
    assert not parse_plain(["G1 X1", "G1 X2\nG1 X3"]).plain.any()


def planned(outputs: list[Output]) -> list[Output]:
    """What a plan depends on: the outputs without follow spindle actions (a line's new S,
    which the move carries as its ``s_value`` too)."""
    kept: list[Output] = []
    for output in outputs:
        if isinstance(output, Move):
            kept.append(replace(output, actions=[a for a in output.actions if not follows(a)]))
        elif not (isinstance(output, Action) and follows(output)):
            kept.append(output)
    return kept


def follows(action: Action) -> bool:
    return action.name == ActionName.SPINDLE and action.lead_s == 0 and not action.stops_motion


def one_by_one(lines: list[str], interpreter: Interpreter) -> tuple[list[Output], object]:
    """The one-line path's outputs up to its first error (as a plan reads them), and that
    error."""
    outputs: list[Output] = []
    for number, text in enumerate(lines, 1):
        try:
            parser.check_length(text, LIMIT_BYTES)
            outputs += interpreter.execute(parse_line(text))
        except CommandError as exc:
            return planned(outputs), (number, exc.code)
    return planned(outputs), None


def in_runs(lines: list[str], interpreter: Interpreter) -> tuple[list[Output], object, int]:
    outputs: list[Output] = []
    where, runs = [0], 0
    try:
        for item in lines_read(lines, interpreter, LIMIT_BYTES, where):
            runs += type(item) is PlainRun
            outputs += item.moves()[0] if type(item) is PlainRun else item
    except CommandError as exc:
        return planned(outputs), (where[0], exc.code), runs
    return planned(outputs), None, runs


def interpreter(soft_limits: bool = False) -> Interpreter:
    settings = InterpreterSettings(("X", "Y", "Z"), (-1e4,) * 3, (1e4,) * 3,
                                   soft_limits=soft_limits)
    made = Interpreter(settings)
    made.set_position((1.0, -2.0, 0.5))
    return made


@pytest.mark.parametrize("seed", range(12))
def test_runs_give_the_moves_and_state_of_the_lines_one_by_one(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(plain, "CHUNK_LINES", 97)  # runs cut by chunks too
    monkeypatch.setattr(plain, "MIN_RUN", 1 + seed % 3)  # and runs of a line or two
    lines = ["G21 G90 G94 M4 S0 F1000", *random_job(seed, 1500)]
    limits = seed % 2 == 1  # soft limits: G91 drifts out of the travel in some
    alone, together = interpreter(limits), interpreter(limits)
    expected, error = one_by_one(lines, alone)
    outputs, run_error, runs = in_runs(lines, together)
    assert runs > (3 if limits else 10), "the runs were taken"
    assert (error is not None) == limits  # (out of the travel within 700 lines)
    assert run_error == error
    assert repr(outputs) == repr(expected)  # (repr: -0.0 is not 0.0)
    assert repr(together.save()) == repr(alone.save())


@pytest.mark.parametrize("text", REFUSED)
def test_a_refused_line_after_a_run_is_refused_at_its_number(text: str) -> None:
    """(A run of 50 lines, then the refused one: both paths stop there.)"""
    lines = ["G21 G90 M4 G1 F600", *[f"X{i % 7} S{i % 3}" for i in range(50)], text, "X1"]
    expected, error = one_by_one(lines, interpreter())
    outputs, run_error, _ = in_runs(lines, interpreter())
    assert error is not None and run_error == error
    assert repr(outputs) == repr(expected)


def test_a_line_over_the_limit_is_refused_though_plain() -> None:
    lines = ["G1 F600 X1", "G1 X" + "1" * 300]
    _, run_error, _ = in_runs(lines, interpreter())
    assert run_error == (2, 11)


def test_inverse_time_and_g91_leave_every_line_to_the_one_line_path(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(plain, "MIN_RUN", 1)
    lines = ["G1 F600 X1", "X2", "X3", "G91", "X1", "X1", "G90 G93", "G1 X5 F10", "X6 F20",
             "G94 G1 F100 X7", "X8"]
    outputs, error, runs = in_runs(lines, interpreter())
    assert runs == 2 and error is None  # the first three lines, and the last
    assert repr(outputs) == repr(one_by_one(lines, interpreter())[0])


@pytest.mark.parametrize("outside", ["X1e4", "Y-10000.5", "Z10001"])
def test_with_soft_limits_a_run_ends_before_the_line_outside_the_travel(
    outside: str, monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(plain, "MIN_RUN", 1)
    lines = ["G1 F600 X1", "X2 Y3", "X9999.9", outside.replace("e4", "0000.001"), "X1"]
    expected, error = one_by_one(lines, interpreter(soft_limits=True))
    outputs, run_error, runs = in_runs(lines, interpreter(soft_limits=True))
    assert runs == 1 and error is not None and run_error == error == (4, error[1])
    assert repr(outputs) == repr(expected)


@pytest.mark.parametrize("chunk_chars", [1, 7, 64, 1 << 16])
def test_file_chunks_give_every_line_and_cut_the_long_ones(chunk_chars: int) -> None:
    long = "X" * 40
    text = f"G1 X1\r\nG1 X2\rG1 X3\n\n{long}\n{long[:11]}\n{long[:12]}\nlast {long}"
    lines = [line for chunk in file_chunks(io.StringIO(text, newline=None), 10, chunk_chars)
             for line in chunk]
    assert lines == ["G1 X1", "G1 X2", "G1 X3", "", long[:11], long[:11], long[:11],
                     f"last {long}"[:11]]


def machine(core: CoreConfig) -> Interpreter:
    """The interpreter a job's plan reads with: the machine's, soft limits off."""
    made = Interpreter(replace(interpreter_settings(core), soft_limits=False))
    made.set_position((0.0,) * len(made.position))
    return made


@pytest.mark.parametrize("seed", range(4))
def test_the_plan_in_runs_is_the_one_line_plan_to_the_bit(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    core = make_config().core
    lines = ["G21 G90 M4 S0 F3000", *random_job(seed, 4000), REFUSED[seed]]
    runs = (estimate(lines, core, interpreter=machine(core), timeline=True),
            extent(lines, core, machine(core)))
    monkeypatch.setattr(plain, "parse_plain", lambda chunk: parser.PlainLines(
        np.zeros(len(chunk), bool), {}))  # every line the one-line path's
    assert offline.lines_read is plain.lines_read
    alone = (estimate(lines, core, interpreter=machine(core), timeline=True),
             extent(lines, core, machine(core)))
    for ran, one in zip(runs, alone, strict=True):
        assert (ran.error, ran.error_line, ran.lines) == (one.error, one.error_line, one.lines)
        assert repr((ran.bbox_min_mm, ran.bbox_max_mm)) == repr((one.bbox_min_mm, one.bbox_max_mm))
    assert runs[0].lines > 100 and runs[0].blocks > 100
    assert (runs[0].duration_s, runs[0].blocks, runs[0].cut_mm, runs[0].rapid_mm) == (
        alone[0].duration_s, alone[0].blocks, alone[0].cut_mm, alone[0].rapid_mm)
    assert np.array_equal(runs[0].timeline(), alone[0].timeline())
