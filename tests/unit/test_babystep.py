"""M290, the babystep: the G92 offset shifted by an amount, the tool moved by it, in order."""

from __future__ import annotations

import math

import pytest

from server.errors import CommandError, SoftLimitError
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import parse_line
from server.motion.moves import Move, MoveKind, Output

XYZ = InterpreterSettings(("X", "Y", "Z"), (-100.0,) * 3, (100.0,) * 3)


def feed(interpreter: Interpreter, *lines: str) -> list[Output]:
    outputs: list[Output] = []
    for text in lines:
        outputs += interpreter.execute(parse_line(text))
    return outputs


def started() -> Interpreter:
    interpreter = Interpreter(XYZ)
    feed(interpreter, "G1 X10 Z-1 F600")
    return interpreter


def test_m290_moves_the_tool_by_the_change_and_shifts_every_later_move() -> None:
    interpreter = started()
    report = interpreter.gc_report()
    step = feed(interpreter, "M290 Z0.05")
    assert [(m.target_mm, m.feed_mm_s, m.kind) for m in step if isinstance(m, Move)] == [
        ((10.0, 0.0, -0.95), math.inf, MoveKind.RAPID)]
    assert len(step) == 1
    assert interpreter.wco() == (0.0, 0.0, 0.05)
    assert interpreter.work_position(interpreter.position) == pytest.approx((10.0, 0.0, -1.0))
    after = feed(interpreter, "X20", "Z-2")
    assert [m.target_mm for m in after if isinstance(m, Move)] == [
        (20.0, 0.0, -0.95), (20.0, 0.0, pytest.approx(-1.95))]
    assert interpreter.gc_report() == report  # the job's modal state is untouched


def test_m290_p0_shifts_the_offset_only_and_the_next_move_naming_the_axis_goes_there() -> None:
    interpreter = started()
    assert feed(interpreter, "M290 Z0.05 P0") == []
    assert interpreter.wco() == (0.0, 0.0, 0.05)
    after = feed(interpreter, "X20", "Z-1")
    assert [m.target_mm for m in after if isinstance(m, Move)] == [
        (20.0, 0.0, -1.0), (20.0, 0.0, -0.95)]


def test_m290_adds_up_is_in_program_units_and_takes_x_and_y() -> None:
    interpreter = started()
    feed(interpreter, "M290 Z0.05", "G20", "M290 X0.1 Z-0.001")
    assert interpreter.wco() == pytest.approx((2.54, 0.0, 0.05 - 0.0254))
    assert interpreter.position == pytest.approx((12.54, 0.0, -1.0 + 0.05 - 0.0254))


def test_a_soft_reset_clears_the_babysteps_with_g92() -> None:
    interpreter = started()
    feed(interpreter, "M290 Z0.05")
    interpreter.reset()
    assert interpreter.wco() == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(("line", "code"), [
    ("M290", 26),  # no axis words
    ("G1 X1 M290 Z1", 24),  # two commands take the axis words
    ("G92 X0 M290 Z1", 24),
    ("M290 Z1 P2", 20),
])
def test_m290_refuses_what_it_cannot_mean(line: str, code: int) -> None:
    interpreter = started()
    before = (interpreter.position, interpreter.wco())
    with pytest.raises(CommandError) as refused:
        feed(interpreter, line)
    assert refused.value.code == code
    assert (interpreter.position, interpreter.wco()) == before


def test_m290_beyond_the_travel_is_refused_as_a_jog_is_without_an_alarm() -> None:
    interpreter = started()
    with pytest.raises(CommandError) as refused:
        feed(interpreter, "M290 Z500")
    assert refused.value.code == 15 and not isinstance(refused.value, SoftLimitError)
    assert interpreter.wco() == (0.0, 0.0, 0.0) and interpreter.position == (10.0, 0.0, -1.0)
