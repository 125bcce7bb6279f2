"""Pure G-code line parser: text line -> :class:`Line` (words, comments, line number, checksum).

No I/O and no state: call :func:`parse_line` with one line of text (without its line ending).
It never raises on bad input; a malformed line comes back with ``error`` set to a
:class:`~server.errors.CommandError` carrying the Grbl error number.

Accepted syntax: words are a letter and a number with optional spaces anywhere
(``G1X10.5Y-3F1500``, ``g1 x 10``); numbers like ``10``, ``-.5``, ``+3.``, ``0.0001``;
``;`` comments to the end of the line and ``( ... )`` comments (kept in ``comments``);
``%`` program markers; ``/`` block delete at the start; RepRap/Smoothie framing
``N123 G1 X5*101`` where the checksum is the XOR of every byte before ``*``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import reduce
from operator import xor

from server.errors import CHECKSUM, CommandError

EXPECTED_COMMAND_LETTER = 1
BAD_NUMBER_FORMAT = 2
REPEATED_WORD = 25
INVALID_LINE_NUMBER = 27
MAX_LINE_NUMBER = 10_000_000

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_WORD = re.compile(rf"([A-Z])({_NUMBER})")
_LETTER = re.compile(r"([A-Z])")
_split_letters = _LETTER.split
_COMMENT = re.compile(r"\(([^)]*)\)|;(.*)", re.S)
_CHECKSUM = re.compile(r"\s*(\d{1,3})\s*")
_REPEATABLE = frozenset("GM")


@dataclass(slots=True)
class Line:
    """One parsed line.

    Attributes:
        text: the line as received, without its line ending.
        words: ``(letter, value)`` pairs in order, letters upper-case, without the ``N`` word.
        comments: the text of ``( ... )`` and ``;`` comments, in order, without delimiters.
        line_number: the value of a leading ``N`` word, if any.
        checksum: the number after ``*``, if any (already validated when ``error`` is None).
        block_delete: the line started with ``/``.
        error: why the line is malformed; such a line must not be executed.
    """

    text: str
    words: list[tuple[str, float]] = field(default_factory=list)
    comments: list[str] = field(default_factory=list)
    line_number: int | None = None
    checksum: int | None = None
    block_delete: bool = False
    error: CommandError | None = None

    def get(self, letter: str) -> float | None:
        """The value of the first word with this letter, or None."""
        for word_letter, value in self.words:
            if word_letter == letter:
                return value
        return None


def checksum_of(text: str) -> int:
    """The RepRap checksum: XOR of every byte of ``text`` (the part before ``*``)."""
    return reduce(xor, text.encode("latin-1", "replace"), 0)


def parse_line(text: str) -> Line:
    """Parse one line of G-code. Never raises; see :class:`Line`."""
    if "*" in text or "(" in text or ";" in text:
        return _parse_framed_or_commented(text)
    # The common line: plain words. Anything unusual falls through to the general path.
    compact = "".join(text.split()).upper()
    parts = _split_letters(compact)
    if compact and not parts[0] and compact.isascii() and "_" not in compact \
            and "N" not in compact:
        letters = parts[1::2]
        try:
            words = list(zip(letters, map(float, parts[2::2]), strict=True))
        except ValueError:
            pass
        else:
            if len(set(letters)) == len(letters):
                return Line(text, words, [], None, None, False, None)
    return _parse_body(Line(text, [], []), text)


def _parse_framed_or_commented(text: str) -> Line:
    line = Line(text, [], [])
    body = text
    if "*" in body:
        body = _split_checksum(line, body)
        if line.error:
            return line
    if "(" in body or ";" in body:
        body = _strip_comments(line, body)
        if line.error:
            return line
    return _parse_body(line, body)


def _parse_body(line: Line, body: str) -> Line:
    compact = "".join(body.split()).upper()
    if compact.startswith("/"):
        line.block_delete = True
        compact = compact[1:]
    if not compact or compact == "%":
        return line
    # Fast path: split on letters and let float() check each number. float() also accepts
    # syntax G-code does not (other scripts' digits, "_" separators; exponents cannot occur
    # since E is a letter), so such lines go to the slow diagnosis.
    parts = _LETTER.split(compact)
    letters = parts[1::2]
    try:
        if parts[0] or not compact.isascii() or "_" in compact:
            raise ValueError
        words = list(zip(letters, map(float, parts[2::2]), strict=True))
    except ValueError:
        line.error = _diagnose(compact)
        return line
    if "N" in compact:
        _take_line_number(line, words)
    if len(set(letters)) != len(letters) and line.error is None:
        line.error = _repeated_word(words)
    line.words = words
    return line


def _split_checksum(line: Line, body: str) -> str:
    before, _, after = body.rpartition("*")
    match = _CHECKSUM.fullmatch(after)
    if match is None:
        line.error = CommandError(CHECKSUM, f"bad checksum field '*{after}'")
        return before
    line.checksum = int(match.group(1))
    expected = checksum_of(before)
    if line.checksum != expected:
        line.error = CommandError(CHECKSUM, f"checksum {line.checksum} != computed {expected}")
    return before


def _strip_comments(line: Line, body: str) -> str:
    kept: list[str] = []
    position = 0
    for match in _COMMENT.finditer(body):
        kept.append(body[position : match.start()])
        paren, semicolon = match.groups()
        if paren is None:
            line.comments.append(semicolon.strip())
            position = len(body)
            break
        line.comments.append(paren.strip())
        position = match.end()
    kept.append(body[position:])
    rest = "".join(kept)
    if "(" in rest:
        line.error = CommandError(EXPECTED_COMMAND_LETTER, "unclosed '(' comment")
    return rest


def _diagnose(compact: str) -> CommandError:
    """Find the first bad character of a line the fast path rejected."""
    position = 0
    while position < len(compact):
        match = _WORD.match(compact, position)
        if match is not None:
            position = match.end()
            continue
        char = compact[position]
        if "A" <= char <= "Z":
            return CommandError(BAD_NUMBER_FORMAT, f"bad number after '{char}'")
        return CommandError(EXPECTED_COMMAND_LETTER, f"expected a command letter, got {char!r}")
    return CommandError(EXPECTED_COMMAND_LETTER, "unparseable line")


def _take_line_number(line: Line, words: list[tuple[str, float]]) -> None:
    for index, (letter, value) in enumerate(words):
        if letter != "N":
            continue
        if index != 0 or value != int(value) or not 0 <= value < MAX_LINE_NUMBER:
            line.error = CommandError(INVALID_LINE_NUMBER, "invalid line number")
            return
        line.line_number = int(value)
        del words[0]
        return


def _repeated_word(words: list[tuple[str, float]]) -> CommandError | None:
    seen: set[str] = set()
    for letter, _ in words:
        if letter in seen and letter not in _REPEATABLE:
            return CommandError(REPEATED_WORD, f"repeated {letter} word")
        seen.add(letter)
    return None
