"""The journal that keeps motiond's interpreter in step with a Grbl board refusing a line."""

from __future__ import annotations

import pytest

from server.backends.grbl.journal import Sent, SentLines
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import parse_line


def machine() -> tuple[Interpreter, SentLines]:
    interpreter = Interpreter(InterpreterSettings(("X", "Y", "Z"), (0.0,) * 3, (300.0,) * 3))
    return interpreter, SentLines(lambda: interpreter)


def send(interpreter: Interpreter, journal: SentLines, text: str) -> Sent:
    """Read a line as the Grbl machine does before sending it."""
    line = parse_line(text)
    before = interpreter.save()
    interpreter.execute(line)
    return journal.add(before, lambda: interpreter.execute(line))


def test_a_refused_line_is_undone_and_the_lines_sent_after_it_are_read_again() -> None:
    interpreter, journal = machine()
    refused = send(interpreter, journal, "G20 G91 G0 X1")
    send(interpreter, journal, "G0 X1")  # read in G20 G91: 50.8 mm
    assert interpreter.position[0] == pytest.approx(50.8)
    journal.refused(refused)
    assert interpreter.gc_report() == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"
    assert interpreter.position == (1.0, 0.0, 0.0), "as the board ran it: 1 mm, absolute"
    assert journal.undone == 1 and len(journal) == 1


def test_an_accepted_line_is_forgotten_and_a_late_refusal_after_a_reset_changes_nothing() -> None:
    interpreter, journal = machine()
    accepted = send(interpreter, journal, "G20")
    late = send(interpreter, journal, "G91")
    journal.answered(accepted)
    journal.clear()  # a reset: the board's buffer is gone
    interpreter.reset()
    journal.refused(late)
    assert interpreter.gc_report() == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"
    assert journal.undone == 0 and len(journal) == 0


def test_a_line_read_again_that_now_fails_changes_nothing_and_waits_for_the_boards_word() -> None:
    interpreter, journal = machine()
    refused = send(interpreter, journal, "G1 F100")
    send(interpreter, journal, "G1 X5")  # needs the feed of the line the board refused
    journal.refused(refused)
    assert interpreter.position == (0.0, 0.0, 0.0)
    assert interpreter.gc_report().startswith("[GC:G0 ")
