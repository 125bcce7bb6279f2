"""The finding of issue 41: a 2-million-line raster took 16-19 s to plan (its fit alone 7-10 s
of CPU), a dozen Python calls per line. A job's plan now reads its plain lines in runs: the
interpreter executes a line alone only when it is not plain (the equivalence of the two
paths: ``test_plain_lines.py``)."""

from __future__ import annotations

from dataclasses import replace

import pytest

from server.gcode.interpreter import Interpreter
from server.machine.parts import interpreter_settings
from server.offline.estimate import estimate, extent
from tests.conftest import make_config

ROWS = 20  # of 1000 0.1 mm segments, each with its own power


def test_the_fit_and_the_plan_read_a_raster_in_runs_not_line_by_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    core = make_config().core
    lines = ["G21 G90 M4 G1 F6000", *[f"G1 X{i % 1000 * 0.1:.1f} Y{i // 1000 * 0.1:.1f} "
                                      f"S{i % 17}" for i in range(ROWS * 1000)]]
    alone = [0]
    execute = Interpreter.execute

    def counted(self: Interpreter, line: object) -> object:
        alone[0] += 1
        return execute(self, line)  # type: ignore[arg-type]

    monkeypatch.setattr(Interpreter, "execute", counted)
    for read in (lambda made: extent(lines, core, made),
                 lambda made: estimate(lines, core, interpreter=made)):
        made = Interpreter(replace(interpreter_settings(core), soft_limits=False))
        made.set_position((0.0,) * len(made.position))
        alone[0] = 0
        stats = read(made)
        assert stats.lines == len(lines) and stats.error is None
        assert alone[0] <= 2, f"{alone[0]} lines of {len(lines)} were read one by one"
