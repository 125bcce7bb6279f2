"""Parser throughput: motiond's parser against PyPI's pygcode, side by side on every corpus file.

Both produce the full output (every word, the line number, comments; motiond also validates
checksums). Two modes: *streaming* parses each line and drops it, as the server does (each
result is touched: letters, values and comments); *retained* keeps every result, which adds
the garbage collector's cost to both. Rounds are interleaved and each parser's best CPU time
counts, so other load on a shared machine does not skew the ratio.
Run: ``python -m benchmarks.bench_parser``.
"""

from __future__ import annotations

import sys

from pygcode import Line as PygcodeLine

from benchmarks.common import corpus_files, side_by_side
from server.gcode import parse_line


def ours_streaming(lines: list[str]) -> None:
    for text in lines:
        line = parse_line(text)
        line.letters, line.values, line.comments  # noqa: B018 - touch the full output


def theirs_streaming(lines: list[str]) -> None:
    for text in lines:
        line = PygcodeLine(text)
        line.block.words, line.comment  # noqa: B018


def main() -> int:
    print(f"{'file':30} {'lines':>7} {'streaming: motiond/s':>21} {'pygcode/s':>10} {'ratio':>6}"
          f" {'retained: ratio':>16}")
    totals = [0.0, 0.0, 0.0, 0.0]
    count = 0
    for path in corpus_files():
        lines = path.read_text(errors="replace").splitlines()
        times = side_by_side(
            3,
            lambda lines=lines: ours_streaming(lines),
            lambda lines=lines: theirs_streaming(lines),
            lambda lines=lines: [parse_line(text) for text in lines],
            lambda lines=lines: [PygcodeLine(text) for text in lines],
        )
        totals = [total + t for total, t in zip(totals, times, strict=True)]
        count += len(lines)
        ours, theirs, ours_kept, theirs_kept = times
        kept_ratio = theirs_kept / ours_kept
        print(f"{path.name:30} {len(lines):7,} {len(lines) / ours:21,.0f} "
              f"{len(lines) / theirs:10,.0f} {theirs / ours:5.1f}x {kept_ratio:15.1f}x")
    ours, theirs, ours_kept, theirs_kept = totals
    print(f"{'all':30} {count:7,} {count / ours:21,.0f} {count / theirs:10,.0f} "
          f"{theirs / ours:5.1f}x {theirs_kept / ours_kept:15.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
