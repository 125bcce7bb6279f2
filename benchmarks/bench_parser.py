"""Parser throughput: motiond's parser against PyPI's pygcode, side by side on every corpus file.

Both produce the full output (every word, the line number, comments; motiond also validates
checksums). Two modes: *streaming* parses each line and drops it, as the server does (each
result is touched: letters, values and comments); *retained* keeps every result, which adds
the garbage collector's cost to both. Rounds are interleaved and each parser's best CPU time
counts, so other load on a shared machine does not skew the ratio (quick: one round, not 3).
Run: ``python -m benchmarks parser [--quick] [--json]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pygcode import Line as PygcodeLine

from benchmarks.common import BenchResult, corpus_files, side_by_side, standalone
from server.gcode.parser import parse_line

ROUNDS = 3
QUICK_ROUNDS = 1


def ours_streaming(lines: list[str]) -> None:
    for text in lines:
        line = parse_line(text)
        line.letters, line.values, line.comments  # noqa: B018 - touch the full output


def theirs_streaming(lines: list[str]) -> None:
    for text in lines:
        line = PygcodeLine(text)
        line.block.words, line.comment  # noqa: B018


def time_file(path: Path, rounds: int) -> tuple[int, list[float]]:
    """Line count, and the best CPU seconds of: ours and pygcode streaming, then retained."""
    lines = path.read_text(errors="replace").splitlines()
    return len(lines), side_by_side(
        rounds,
        lambda: ours_streaming(lines),
        lambda: theirs_streaming(lines),
        lambda: [parse_line(text) for text in lines],
        lambda: [PygcodeLine(text) for text in lines],
    )


def report(result: BenchResult, label: str, count: int, times: list[float]) -> None:
    """Print one table row and record its figures."""
    ours, theirs, ours_kept, theirs_kept = times
    print(f"{label:30} {count:7,} {count / ours:21,.0f} {count / theirs:10,.0f} "
          f"{theirs / ours:5.1f}x {theirs_kept / ours_kept:15.1f}x")
    result.add("corpus", label, lines=(count, "lines"),
               motiond_streaming=(count / ours, "lines/s"),
               pygcode_streaming=(count / theirs, "lines/s"),
               ratio_streaming=(theirs / ours, "x"),
               motiond_retained=(count / ours_kept, "lines/s"),
               pygcode_retained=(count / theirs_kept, "lines/s"),
               ratio_retained=(theirs_kept / ours_kept, "x"))


def run(quick: bool) -> BenchResult:
    result = BenchResult("parser", quick)
    print(f"{'file':30} {'lines':>7} {'streaming: motiond/s':>21} {'pygcode/s':>10} {'ratio':>6}"
          f" {'retained: ratio':>16}")
    totals = [0.0, 0.0, 0.0, 0.0]
    count = 0
    for path in corpus_files():
        lines, times = time_file(path, QUICK_ROUNDS if quick else ROUNDS)
        report(result, path.name, lines, times)
        totals = [total + t for total, t in zip(totals, times, strict=True)]
        count += lines
    report(result, "all", count, totals)
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
