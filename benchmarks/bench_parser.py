"""Parser throughput: motiond's parser against PyPI's pygcode, side by side on every corpus file.

Both produce the full output (every word, the line number, comments; motiond also validates
checksums). Rounds are interleaved and each parser's best CPU time counts, so other load on a
shared machine does not skew the ratio. Run: ``python -m benchmarks.bench_parser``.
"""

from __future__ import annotations

import sys

from pygcode import Line as PygcodeLine

from benchmarks.common import corpus_files, side_by_side
from server.gcode import parse_line


def main() -> int:
    print(f"{'file':32} {'lines':>7} {'motiond lines/s':>16} {'pygcode lines/s':>16} {'ratio':>7}")
    total_ours = total_theirs = 0.0
    total_lines = 0
    for path in corpus_files():
        lines = path.read_text(errors="replace").splitlines()
        ours, theirs = side_by_side(
            3,
            lambda lines=lines: [parse_line(text) for text in lines],
            lambda lines=lines: [PygcodeLine(text) for text in lines],
        )
        total_ours, total_theirs, total_lines = total_ours + ours, total_theirs + theirs, \
            total_lines + len(lines)
        print(f"{path.name:32} {len(lines):7,} {len(lines) / ours:16,.0f} "
              f"{len(lines) / theirs:16,.0f} {theirs / ours:6.1f}x")
    print(f"{'all':32} {total_lines:7,} {total_lines / total_ours:16,.0f} "
          f"{total_lines / total_theirs:16,.0f} {total_theirs / total_ours:6.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
