"""Every corpus file through parse_line + Interpreter on a generous XYZ machine (soft limits on).

A file is run the way a Grbl sender streams it: line by line, stopping at the first error.
Lines whose M code a module claims (fans, output pins, overrides) are routed to that module by
the dispatcher and never reach the interpreter; the test skips them the same way.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from server.errors import CommandError
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import Line, parse_line
from tests.conftest import CORPUS

MACHINE = InterpreterSettings(("X", "Y", "Z"), (-1000.0,) * 3, (1000.0,) * 3, soft_limits=True)
MODULE_M_CODES = frozenset({42, 106, 107, 221})  # switch pin, fan on/off, flow override

# file -> None when every line is accepted, else (1-based line number, Grbl error, line text).
EXPECTED: dict[str, tuple[int, int, str] | None] = {
    "cnc-arcs-arrows.nc": None,
    # N624 G3 X21 Y-20 I20 J21: centre (40, 0), start radius 29, end radius 27.586 (1.41 mm off
    # the circle, a sign slip in the file: I-20 would be right). Grbl refuses it as well.
    "cnc-calibration-arcs.gcode": (624, 33, "N624 G3 X21 Y-20 I20 J21"),
    "cnc-helical-thread.gcode": (5, 20, "G42 D08"),
    "laser-engrave-tball.gcode": None,
    "laser-raster-tree.nc": None,
    "laser-vector-jsdc.gcode": None,
    # line 10 is M107 (fan off: a module's); line 11 M104 S200 is the first temperature code.
    "printer-sample.gcode": (11, 20, "M104 S200 ; set temperature"),
}
FINAL_POSITION = {
    "cnc-arcs-arrows.nc": (0.0, 0.0, 5.0),
    "laser-engrave-tball.gcode": (0.0, 0.0, 0.0),
    "laser-raster-tree.nc": (61.0, 98.333, 0.0),
    "laser-vector-jsdc.gcode": (0.0, 0.0, 0.0),
}


def corpus_lines(name: str) -> list[str]:
    return Path(CORPUS, name).read_text(encoding="utf-8").splitlines()


def claimed_by_a_module(line: Line) -> bool:
    return any(letter == "M" and value in MODULE_M_CODES for letter, value in line.words)


def stream(name: str, interpreter: Interpreter) -> tuple[int, int, str] | None:
    """Run a file until its first error; that error's line number, code and text, or None."""
    for number, text in enumerate(corpus_lines(name), start=1):
        line = parse_line(text)
        if claimed_by_a_module(line):
            continue
        try:
            interpreter.execute(line)
        except CommandError as error:
            return number, error.code, text.strip()
    return None


def test_every_corpus_file_has_an_expected_outcome() -> None:
    files = {path.name for path in Path(CORPUS).iterdir() if path.suffix in (".nc", ".gcode")}
    assert files == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_corpus_file_runs_to_its_expected_outcome(name: str) -> None:
    interpreter = Interpreter(MACHINE)
    assert stream(name, interpreter) == EXPECTED[name]
    if name in FINAL_POSITION:
        assert interpreter.position == pytest.approx(FINAL_POSITION[name])


def test_helical_thread_stops_at_the_g42_line_with_a_clear_message() -> None:
    lines = corpus_lines("cnc-helical-thread.gcode")
    number = next(i for i, text in enumerate(lines, start=1) if text.startswith("G42"))
    assert number == 5
    interpreter = Interpreter(MACHINE)
    for text in lines[: number - 1]:
        interpreter.execute(parse_line(text))
    with pytest.raises(CommandError) as caught:
        interpreter.execute(parse_line(lines[number - 1]))
    assert caught.value.code == 20
    assert "G42" in caught.value.message and "compensation" in caught.value.message


def test_printer_sample_fails_at_its_first_temperature_or_extruder_line() -> None:
    lines = corpus_lines("printer-sample.gcode")
    first = next(i for i, text in enumerate(lines, start=1)
                 if any(w[0] in ("M", "E") and (w[0] == "E" or w[1] in (104.0, 109.0))
                        for w in parse_line(text).words))
    assert first == 11
    assert stream("printer-sample.gcode", Interpreter(MACHINE)) == (first, 20, lines[10].strip())


def test_printer_sample_without_a_fan_module_fails_at_m107() -> None:
    interpreter = Interpreter(MACHINE)
    lines = corpus_lines("printer-sample.gcode")
    for text in lines[:9]:
        interpreter.execute(parse_line(text))
    with pytest.raises(CommandError) as caught:
        interpreter.execute(parse_line(lines[9]))
    assert (lines[9], caught.value.code) == ("M107", 20)


def test_calibration_file_streamed_past_errors_refuses_only_its_five_bad_arcs() -> None:
    interpreter, refused = Interpreter(MACHINE), []
    for number, text in enumerate(corpus_lines("cnc-calibration-arcs.gcode"), start=1):
        try:
            interpreter.execute(parse_line(text))
        except CommandError as error:
            refused.append((number, error.code))
    assert refused == [(624, 33), (696, 33), (768, 33), (840, 33), (912, 33)]


def test_the_raster_job_carries_a_new_s_on_nearly_every_move() -> None:
    interpreter = Interpreter(MACHINE)
    s_values = []
    for text in corpus_lines("laser-raster-tree.nc"):
        for output in interpreter.execute(parse_line(text)):
            if hasattr(output, "s_value"):
                s_values.append(output.s_value)
    assert len(s_values) > 50_000
    assert len(set(s_values)) > 50
