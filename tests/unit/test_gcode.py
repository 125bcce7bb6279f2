"""The pure G-code parser: words, comments, framing and Grbl error numbers."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.errors import CommandError
from server.gcode import _words, parser
from server.gcode.parser import _parse_framed_or_commented, checksum_of, parse_line
from tests.unit.test_plain_lines import corpus_lines


@pytest.mark.parametrize(
    "text, words",
    [
        ("G1X10.5Y-3F1500", [("G", 1), ("X", 10.5), ("Y", -3), ("F", 1500)]),
        ("g1 x10", [("G", 1), ("X", 10)]),
        ("G0 X-.5 Y+3. Z0.0001", [("G", 0), ("X", -0.5), ("Y", 3), ("Z", 0.0001)]),
        ("G 1 X 1 0", [("G", 1), ("X", 10)]),
        ("G90 G21 G17 M3 S1000", [("G", 90), ("G", 21), ("G", 17), ("M", 3), ("S", 1000)]),
        ("G38.2 Z-10 F100", [("G", 38.2), ("Z", -10), ("F", 100)]),
        ("\tG1\tX1  ", [("G", 1), ("X", 1)]),
    ],
)
def test_words_are_a_letter_and_a_number_with_optional_spaces(text: str, words: list) -> None:
    line = parse_line(text)
    assert line.error is None
    assert line.words == words


def test_comments_are_kept_and_removed_from_words() -> None:
    line = parse_line("G1 (MSG, hello) X1 ; the rest (ignored")
    assert line.words == [("G", 1), ("X", 1)]
    assert line.comments == ("MSG, hello", "the rest (ignored")


def test_empty_comment_only_and_percent_lines_have_no_words() -> None:
    for text in ("", "   ", "(comment)", "; comment", "%"):
        line = parse_line(text)
        assert line.error is None and line.words == []


def test_block_delete_is_flagged() -> None:
    line = parse_line("/G0 X1")
    assert line.block_delete and line.words == [("G", 0), ("X", 1)]


def test_line_number_and_valid_checksum() -> None:
    body = "N12 G1 X5"
    line = parse_line(f"{body}*{checksum_of(body)}")
    assert line.error is None
    assert (line.line_number, line.checksum) == (12, checksum_of(body))
    assert line.words == [("G", 1), ("X", 5)]


def test_printrun_m110_framing_checksum() -> None:
    assert parse_line("N0 M110 N0*125").error is None


def test_bad_checksum_is_reported_not_executed() -> None:
    line = parse_line("N3 G1 X1*99")
    assert line.error is not None and line.error.code == 41
    assert line.words == []


@pytest.mark.parametrize(
    "text, code",
    [
        ("G1 X", 2),  # bad number format
        ("G1 X1..2", 1),
        ("#1=2", 1),  # expected command letter
        ("G1 X1 X2", 25),  # repeated word
        ("G1 N5", 27),  # line number not first
        ("N1.5 G1", 27),
        ("G1 X1*", 41),
    ],
)
def test_malformed_lines_get_grbl_error_numbers(text: str, code: int) -> None:
    error = parse_line(text).error
    assert isinstance(error, CommandError)
    assert error.code == code


def test_an_unclosed_comment_runs_to_the_end_of_the_line_as_in_grbl() -> None:
    line = parse_line("G1 X1 (unclosed Y2")
    assert line.error is None and line.words == [("G", 1.0), ("X", 1.0)]
    assert line.comments == ("unclosed Y2",)


def test_repeated_g_and_m_words_are_left_to_the_interpreter() -> None:
    assert parse_line("G90 G91").error is None
    assert parse_line("M3 M8").error is None


@given(st.text(max_size=120))
def test_any_text_parses_without_raising(text: str) -> None:
    line = parse_line(text)
    assert line.error is None or isinstance(line.error, CommandError)
    if line.error is None:
        assert all(letter.isupper() and len(letter) == 1 for letter, _ in line.words)


@given(st.lists(st.tuples(st.sampled_from("GMXYZFS"), st.floats(-1e4, 1e4)), max_size=6))
def test_formatted_words_parse_back_to_their_values(words: list[tuple[str, float]]) -> None:
    text = " ".join(f"{letter}{value:.4f}" for letter, value in words)
    line = parse_line(text)
    letters = [letter for letter, _ in words if letter not in "GM"]
    if len(set(letters)) != len(letters):
        assert line.error is not None and line.error.code == 25
        return
    assert line.error is None
    assert [(k, round(v, 4)) for k, v in line.words] == [
        (k, round(float(f"{v:.4f}"), 4)) for k, v in words]


@pytest.mark.parametrize(
    "text, code",
    [
        ("X Y1 2", 2),  # X has no number: the space must not pair X with 1
        ("5XY1", 1),  # something before the first letter
        ("G1 X1_0", 1),  # float() accepts "1_0"; G-code does not
        ("G1 X١", 1),  # nor other scripts' digits
        ("G1 X1 ;c", None),
        ("G1 X1\x0b", None),
    ],
)
def test_the_fast_path_refuses_what_float_alone_would_accept(text: str, code: int | None) -> None:
    line = parse_line(text)
    assert (line.error.code if line.error else None) == code
    if code is None:
        assert line.words == [("G", 1), ("X", 1)]


_GCODE_ALPHABET = st.sampled_from("GgXxYNM0123456789.-+ _*;()%/\t#E")


@given(st.text(_GCODE_ALPHABET, max_size=40))
def test_the_fast_path_agrees_with_the_general_path(text: str) -> None:
    fast, general = parse_line(text), _parse_framed_or_commented(text)
    assert (fast.letters, fast.values, fast.line_number, fast.comments, fast.block_delete) == (
        general.letters, general.values, general.line_number, general.comments,
        general.block_delete)
    assert (fast.error and fast.error.code) == (general.error and general.error.code)


def test_the_plain_line_is_read_in_c() -> None:
    """The install builds the extension, and parse_line reads plain lines with it."""
    assert parser._plain_words is _words.words
    assert _words.words("g1 x 1 0 Y-.5") == ("GXY", [1.0, 10.0, -0.5])
    assert _words.words("G1 X1 ;c") is None and _words.words("") is None


def test_every_corpus_line_reads_alike_on_the_fast_and_the_general_path() -> None:
    lines = [*corpus_lines(),
             "G1 X0." + "0" * 70 + "1",  # longer than the C path reads: the general path's
             "G1 X1000000000 Y1000000000",  # each at the bound, not above
             "G1 X1e5", "G1 X1.2.3", "G1 X+-1", "G1 X.", "G1 X-", "N7 G1 X1", "G1X1X2", "G1 X1 F"]
    assert [text for text in lines if _read(parse_line(text)) != _read(
        _parse_framed_or_commented(text))] == []


def _read(line: parser.Line) -> tuple[object, ...]:
    return (line.letters, line.values, line.line_number, line.comments, line.block_delete,
            line.error and line.error.code)


HUGE = "1" + "0" * 400  # float() turns it into infinity


@pytest.mark.parametrize(
    "text, letter",
    [
        (f"G1 X1 F{HUGE}", "F"),  # the fast path
        (f"G1 X1 F{HUGE} (comment)", "F"),  # the general path
        (f"N5 G4 P-{HUGE}*0", None),  # framed: the checksum is checked first (error 41)
        ("G1 X1000000000.001", "X"),
        ("G1 X-2000000000 Y1", "X"),
        (f"G2 X10 R1{'0' * 200}", "R"),
    ],
)
def test_numbers_that_are_not_finite_or_too_large_are_a_bad_number_format(
    text: str, letter: str | None
) -> None:
    line = parse_line(text)
    assert line.error is not None and line.letters == "" and line.values == []
    if letter is None:
        assert line.error.code == 41
        return
    assert line.error.code == 2 and f"'{letter}'" in line.error.message
    assert _parse_framed_or_commented(text).error.code == 2


def test_numbers_up_to_the_bound_parse_even_when_their_sum_is_larger() -> None:
    line = parse_line("G1 X1000000000 Y-1000000000 F999999999.5")
    assert line.error is None and line.values == [1.0, 1e9, -1e9, 999999999.5]


@pytest.mark.parametrize("text", ["G1 Xinf", "G1 Xnan", "G1 X-Infinity", "G1 X1e400 Y0"])
def test_words_spelling_infinities_never_become_numbers(text: str) -> None:
    line = parse_line(text)
    assert line.error is not None or (line.values == [1.0, 1.0, 400.0, 0.0] and "E" in line.letters)
    assert all(abs(value) <= 1e9 for value in line.values)
