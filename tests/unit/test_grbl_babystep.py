"""M290 as the lines a Grbl 1.1 board runs (babystep_lines), read from motiond's interpreter."""

from __future__ import annotations

import pytest

from server.backends.grbl.babystep import babystep_lines
from server.errors import CommandError, Error
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import parse_line


def lines_for(*texts: str) -> list[str]:
    """Read ``texts`` (the last one an M290) as the grbl machine does; the board's lines."""
    interpreter = Interpreter(InterpreterSettings(("X", "Y", "Z"), (-300.0,) * 3, (300.0,) * 3))
    for text in texts:
        interpreter.execute(parse_line(text))
    return babystep_lines(parse_line(texts[-1]), interpreter)


def test_a_move_goes_to_the_machine_target_and_keeps_the_work_position() -> None:
    assert lines_for("G10 L2 P1 Z-10", "G0 Z5", "M290 Z0.05") == ["G53G0Z-4.95", "G92Z5"]


def test_p0_sets_the_offset_only_and_the_work_position_moves_the_other_way() -> None:
    assert lines_for("G0 Z5", "M290 Z0.05 P0") == ["G92Z4.95"]


def test_g1_is_restored_after_the_rapid_and_g80_around_it() -> None:
    assert lines_for("G1 Z5 F100", "M290 Z-0.1") == ["G53G0Z4.9", "G92Z5", "G1"]
    assert lines_for("G80", "M290 Z0.1") == ["G53G0Z0.1", "G92Z0", "G80"]
    assert lines_for("G80", "M290 Z0.1 P0") == ["G0", "G92Z-0.1", "G80"], "G80 refuses G92 Z"


def test_inches_and_increments_are_the_programs_and_g53_ignores_g91() -> None:
    assert lines_for("G20 G91 G0 Z1", "G92 Z0", "M290 Z0.01") == [
        "G53G0Z1.01", "G92Z0"]
    assert lines_for("G20 G0 X1 Y2", "M290 X0.001 Y-0.002") == [
        "G53G0X1.001Y1.998", "G92X1Y2"]


def test_the_existing_g92_offset_and_tool_length_are_part_of_the_work_position() -> None:
    assert lines_for("G0 Z10", "G92 Z2", "G43.1 Z1", "M290 Z0.5") == ["G53G0Z10.5", "G92Z1"]


@pytest.mark.parametrize("modes", [("G2 X0 Y0 I1 J0 F100",), ("G38.2 Z-1 F100",),
                                   ("G1 X1 F100", "F0"), ("G93 G1 X1 F2",),
                                   ("G93 G1 X1 F2", "G94")])
def test_a_mode_grbl_cannot_restore_without_a_move_is_refused(modes: tuple[str, ...]) -> None:
    with pytest.raises(CommandError) as refused:
        lines_for(*modes, "M290 Z0.1")
    assert refused.value.code in (Error.UNSUPPORTED, Error.UNDEFINED_FEED)
    assert "M290 on a Grbl board" in refused.value.message
    assert lines_for(*modes, "M290 Z0.1 P0")[0].startswith("G92Z"), "P0 needs no restore"


@pytest.mark.parametrize("text", ["M290 Z0.1 F100", "G21 M290 Z0.1", "M290 M5 Z0.1",
                                  "M290 Z0.1 S5"])
def test_other_words_on_the_line_are_refused(text: str) -> None:
    with pytest.raises(CommandError, match="a line of its own"):
        lines_for(text)
