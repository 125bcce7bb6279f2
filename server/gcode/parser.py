"""Pure G-code line parser: text line -> :class:`Line` (words, comments, line number, checksum).

No I/O and no state: call :func:`parse_line` with one line of text (without its line ending).
It never raises on bad input; a malformed line comes back with ``error`` set to a
:class:`~server.errors.CommandError` carrying the Grbl error number.

Accepted syntax: words are a letter and a number with optional spaces anywhere
(``G1X10.5Y-3F1500``, ``g1 x 10``); numbers like ``10``, ``-.5``, ``+3.``, ``0.0001``;
``;`` comments to the end of the line and ``( ... )`` comments (kept in ``comments``);
``%`` program markers; ``/`` block delete at the start; RepRap/Smoothie framing
``N123 G1 X5*101`` where the checksum is the XOR of every byte before ``*``.

Every value is finite and at most :data:`MAX_MAGNITUDE` in size: a number too long to be a
float (``F1`` and 400 zeros, which float() turns into infinity) or too large for any machine
quantity is a bad number format (error 2), on the fast path as on the general one.

The fast path, a line of plain words (most lines), is C (``_words.c``: one call, where Python
took a dozen); the general path reads every other line and finds the errors. Both read every
line alike (tests/unit/test_gcode.py).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce
from itertools import compress
from math import hypot
from operator import xor

import numpy as np

from server.errors import CommandError, Error

try:  # the plain line's words in C, built by pip install where a C compiler is
    from server.gcode._words import words as _plain_words
except ImportError:  # without it every line takes the general path: slower, read alike
    def _plain_words(text: str, /) -> tuple[str, list[float]] | None:
        return None

MAX_LINE_NUMBER = 10_000_000
# No G-code quantity is larger: 1e9 mm is 1000 km, 1e9 mm/min is 17 km/s. The bound keeps every
# step count (at most 1e6 steps/mm, see AxisConfig) exactly representable in a float, and
# keeps unit scaling (x 25.4) and squares (v^2, 2 a d) far from overflowing.
MAX_MAGNITUDE = 1e9

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_WORD = re.compile(rf"([A-Z])({_NUMBER})")
_LETTER = re.compile(r"([A-Z])")
_split_letters = _LETTER.split
_COMMENT = re.compile(r"\(([^)]*)\)|;(.*)", re.S)
_CHECKSUM = re.compile(r"\s*(\d{1,3})\s*")
_REPEATABLE = frozenset("GM")

_UPPER, _LOWER = b"ABCDEFGHIJKLMNOPQRSTUVWXYZ", b"abcdefghijklmnopqrstuvwxyz"
_TO_UPPER = bytes.maketrans(_LOWER, _UPPER)

# Byte classes of the batch path (see parse_plain): a number's characters, a letter, a line's
# end; everything else (comments, checksums, tabs, "_", "%", "/", non-ASCII) is a stranger.
_STRANGER, _LETTER_BYTE, _NUMBER_BYTE, _END = 0, 1, 2, 3
_CLASS = np.zeros(256, np.uint8)
_CLASS[np.frombuffer(_UPPER, np.uint8)] = _LETTER_BYTE
_CLASS[np.frombuffer(b"0123456789.+-", np.uint8)] = _NUMBER_BYTE
_CLASS[ord("\n")] = _END
_ONLY_NUMBERS = bytes(code if _CLASS[code] == _NUMBER_BYTE else 32 for code in range(256))


class Line:
    """One parsed line.

    The words are kept as a string of letters and a parallel list of values, so that parsing
    a line allocates no object per word; :attr:`words` pairs them up when that reads better.

    Attributes:
        text: the line as received, without its line ending.
        letters: the word letters in order, upper-case, without the ``N`` word (``"GXY"``).
        values: the number of each word, parallel to ``letters``.
        comments: the text of ``( ... )`` and ``;`` comments, in order, without delimiters.
        line_number: the value of a leading ``N`` word, if any.
        checksum: the number after ``*``, if any (already validated when ``error`` is None).
        block_delete: the line started with ``/``.
        error: why the line is malformed; such a line must not be executed.
    """

    __slots__ = ("text", "letters", "values", "comments", "line_number", "checksum",
                 "block_delete", "error")

    def __init__(self, text: str, letters: str, values: list[float]) -> None:
        self.text = text
        self.letters = letters
        self.values = values
        self.comments: tuple[str, ...] = ()
        self.line_number: int | None = None
        self.checksum: int | None = None
        self.block_delete = False
        self.error: CommandError | None = None

    @classmethod
    def of(cls, text: str, words: list[tuple[str, float]]) -> Line:
        """A line made from ``(letter, value)`` pairs (for tests and synthesised lines)."""
        return cls(text, "".join(letter for letter, _ in words), [value for _, value in words])

    @property
    def words(self) -> list[tuple[str, float]]:
        """``(letter, value)`` pairs in order."""
        return list(zip(self.letters, self.values, strict=True))

    def get(self, letter: str) -> float | None:
        """The value of the first word with this letter, or None."""
        for word_letter, value in zip(self.letters, self.values, strict=True):
            if word_letter == letter:
                return value
        return None

    def __repr__(self) -> str:
        return f"Line({self.text!r}, words={self.words}, error={self.error})"


def checksum_of(text: str) -> int:
    """The RepRap checksum: XOR of every byte of ``text`` (the part before ``*``)."""
    return reduce(xor, text.encode("latin-1", "replace"), 0)


def parse_line(text: str) -> Line:
    """Parse one line of G-code. Never raises; see :class:`Line`."""
    # The common line, plain words, is read in C in one call (``_words.c``); any other line
    # (a comment, a checksum, a stray character, an error) takes the general path, which also
    # finds the error: so does every line when the extension was not built.
    plain = _plain_words(text)
    if plain is None:
        return _parse_framed_or_commented(text)
    line = Line(text, *plain)
    if "N" in plain[0]:
        _take_line_number(line)
    return line


@dataclass(frozen=True, slots=True)
class PlainLines:
    """Many lines parsed at once by :func:`parse_plain`.

    Attributes:
        plain: per line, whether it is plain: it parses on :func:`parse_line`'s fast path
            without a line number, so its :class:`Line` has no error, comment or checksum.
        columns: per letter (upper-case), the value of that word on each plain line (NaN
            where the line has no such word, and on every line that is not plain).
    """

    plain: np.ndarray
    columns: dict[str, np.ndarray]


def parse_plain(lines: Sequence[str]) -> PlainLines:
    """Parse the plain lines among ``lines`` (each without its ending) at once, as
    :func:`parse_line` parses them one by one (the same bytes through the same ``float``),
    with a few numpy passes over them all instead of a dozen calls per line: what a job's
    plan reads two million lines with. A line that is not plain is left for
    :func:`parse_line` (which also finds its error)."""
    count = len(lines)
    compact = ("\n".join(lines) + "\n").encode("ascii", "replace").translate(_TO_UPPER, b" ")
    chars = np.frombuffer(compact, np.uint8)
    kinds = _CLASS[chars]
    ends = np.flatnonzero(kinds == _END)
    if ends.shape[0] != count:  # a line with an ending of its own inside: none is plain
        return PlainLines(np.zeros(count, bool), {})
    first = np.empty(count, np.intp)  # where each line begins (each ends with its "\n")
    first[:1], first[1:] = 0, ends[:-1] + 1
    is_letter = kinds == _LETTER_BYTE
    starts = kinds == _NUMBER_BYTE
    starts[1:] &= kinds[:-1] != _NUMBER_BYTE  # where a number begins
    plain, letter_lines, token_lines = _shapes(kinds, is_letter, starts, first)
    letters = chars[is_letter]
    plain[letter_lines[letters == ord("N")]] = False  # a line number: the one-line path's
    keep = plain[token_lines]
    values = _floats(list(compress(compact.translate(_ONLY_NUMBERS).split(), keep)))
    letters, owners = letters[plain[letter_lines]], token_lines[keep]  # a letter per number
    plain[owners[~(np.abs(values) <= MAX_MAGNITUDE)]] = False  # NaN: a token float() refused
    keys = np.sort(owners * 32 + (letters - ord("A")))
    plain[keys[1:][keys[1:] == keys[:-1]] // 32] = False  # a repeated word
    kept = plain[owners]
    return PlainLines(plain, _columns(letters[kept], owners[kept], values[kept], count))


def _shapes(kinds: np.ndarray, is_letter: np.ndarray, starts: np.ndarray,
            first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which lines have the shape of a plain one (a letter first, no stranger, as many
    numbers as letters: a letter then a number, each time), and the line of every letter and
    every number."""
    letters_per_line = np.add.reduceat(is_letter, first, dtype=np.int32)
    numbers_per_line = np.add.reduceat(starts, first, dtype=np.int32)
    plain = is_letter[first]  # (an empty line: its ending first)
    plain &= np.add.reduceat(kinds == _STRANGER, first, dtype=np.int32) == 0
    plain &= letters_per_line == numbers_per_line
    lines = np.arange(first.shape[0])
    return plain, np.repeat(lines, letters_per_line), np.repeat(lines, numbers_per_line)


def _columns(letters: np.ndarray, owners: np.ndarray, values: np.ndarray,
             count: int) -> dict[str, np.ndarray]:
    """Per letter, its value on each line (``owners``), NaN on the others."""
    columns = {}
    for code in np.unique(letters).tolist():
        column = np.full(count, np.nan)
        here = letters == code
        column[owners[here]] = values[here]
        columns[chr(code)] = column
    return columns


def _floats(tokens: list[bytes]) -> np.ndarray:
    """Each number as ``float()`` reads it; NaN for one it refuses ("1.2.3", "+")."""
    try:
        return np.fromiter(map(float, tokens), np.float64, len(tokens))
    except ValueError:
        return np.array([_float_or_nan(token) for token in tokens], np.float64)


def _float_or_nan(token: bytes) -> float:
    try:
        return float(token)
    except ValueError:
        return math.nan


def too_long(text: str, limit_bytes: int) -> bool:
    """Whether ``text`` (a line without its ending) is over ``limit_bytes`` in UTF-8."""
    return len(text) > limit_bytes or (
        4 * len(text) > limit_bytes and len(text.encode("utf-8", "replace")) > limit_bytes
    )


def check_length(text: str, limit_bytes: int) -> None:
    """Refuse a line over the limit as the line protocol does (Grbl's ``error:11``), for the
    entry paths that do not go through it (the API's ``gcode.send``, job files)."""
    if too_long(text, limit_bytes):
        raise CommandError(Error.LINE_OVERFLOW, f"line longer than {limit_bytes} bytes")


def _parse_framed_or_commented(text: str) -> Line:
    line = Line(text, "", [])
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
    # Split on letters and let float() check each number. float() also accepts syntax G-code
    # does not (other scripts' digits, "_" separators; exponents cannot occur since E is a
    # letter), so such lines go to the slow diagnosis.
    parts = _split_letters(compact)
    letters = "".join(parts[1::2])
    try:
        if parts[0] or not compact.isascii() or "_" in compact:
            raise ValueError
        values = list(map(float, parts[2::2]))
    except ValueError:
        line.error = _diagnose(compact)
        return line
    if not hypot(*values) <= MAX_MAGNITUDE:
        line.error = _out_of_range(letters, values)
        if line.error is not None:
            return line
    line.letters, line.values = letters, values
    if "N" in letters:
        _take_line_number(line)
    if len(set(line.letters)) != len(line.letters) and line.error is None:
        line.error = _repeated_word(line.letters)
    return line


def _split_checksum(line: Line, body: str) -> str:
    before, _, after = body.rpartition("*")
    match = _CHECKSUM.fullmatch(after)
    if match is None:
        line.error = CommandError(Error.CHECKSUM, f"bad checksum field '*{after}'")
        return before
    line.checksum = int(match.group(1))
    expected = checksum_of(before)
    if line.checksum != expected:
        line.error = CommandError(
            Error.CHECKSUM, f"checksum {line.checksum} != computed {expected}"
        )
    return before


def _strip_comments(line: Line, body: str) -> str:
    kept: list[str] = []
    comments: list[str] = []
    position = 0
    for match in _COMMENT.finditer(body):
        kept.append(body[position : match.start()])
        paren, semicolon = match.groups()
        if paren is None:
            comments.append(semicolon.strip())
            position = len(body)
            break
        comments.append(paren.strip())
        position = match.end()
    kept.append(body[position:])
    rest = "".join(kept)
    if "(" in rest:  # unclosed: a comment to the end of the line, as Grbl reads it
        rest, _, comment = rest.partition("(")
        comments.append(comment.strip())
    line.comments = tuple(comments)
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
            return CommandError(Error.BAD_NUMBER_FORMAT, f"bad number after '{char}'")
        return CommandError(
            Error.EXPECTED_COMMAND_LETTER, f"expected a command letter, got {char!r}"
        )
    return CommandError(Error.EXPECTED_COMMAND_LETTER, "unparseable line")


def _out_of_range(letters: str, values: list[float]) -> CommandError | None:
    """Error 2 for the first value that is not finite or is larger than MAX_MAGNITUDE."""
    for letter, value in zip(letters, values, strict=True):
        if not -MAX_MAGNITUDE <= value <= MAX_MAGNITUDE:  # also false for NaN
            return CommandError(Error.BAD_NUMBER_FORMAT, f"number after '{letter}' out of range")
    return None


def _take_line_number(line: Line) -> None:
    value = line.values[0]
    if line.letters[0] != "N" or value != int(value) or not 0 <= value < MAX_LINE_NUMBER:
        line.error = CommandError(Error.INVALID_LINE_NUMBER, "invalid line number")
        return
    line.line_number = int(value)
    line.letters, line.values = line.letters[1:], line.values[1:]


def _repeated_word(letters: str) -> CommandError | None:
    seen: set[str] = set()
    for letter in letters:
        if letter in seen and letter not in _REPEATABLE:
            return CommandError(Error.REPEATED_WORD, f"repeated {letter} word")
        seen.add(letter)
    return None
