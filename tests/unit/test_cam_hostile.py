"""Hostile drawings are refused with a message naming what and where, within bounded time
and memory: entity bombs and external entities in SVG, a path of a million points, an image
of 100,000 x 100,000 pixels, a DXF with an entity motiond does not cut, XML cut short."""

from __future__ import annotations

import io
import struct
import time
import tracemalloc
import zlib
from collections.abc import Callable

import ezdxf
import pytest

from server.cam.job import read_drawing
from server.errors import DrawingError

BILLION_LAUGHS = b"""<?xml version="1.0"?>
<!DOCTYPE svg [
 <!ENTITY a "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa">
 <!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">
 <!ENTITY c "&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;">
 <!ENTITY d "&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;&c;">
]>
<svg xmlns="http://www.w3.org/2000/svg"><desc>&d;</desc></svg>
"""
EXTERNAL = b"""<?xml version="1.0"?>
<!DOCTYPE svg [<!ENTITY secret SYSTEM "file:///etc/passwd">]>
<svg xmlns="http://www.w3.org/2000/svg"><text>&secret;</text></svg>
"""


def _refused(read: Callable[[], object], bound_s: float = 2.0,
             bound_bytes: int = 64 << 20) -> str:
    """The message of the refusal; asserts it came within the time and memory bounds."""
    tracemalloc.start()
    started = time.perf_counter()
    try:
        with pytest.raises(DrawingError) as refused:
            read()
        elapsed_s = time.perf_counter() - started
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert elapsed_s < bound_s, f"refused after {elapsed_s:.2f} s"
    assert peak < bound_bytes, f"refused after allocating {peak / 1e6:.0f} MB"
    return str(refused.value)


def test_an_entity_expansion_bomb_is_refused_naming_the_line() -> None:
    message = _refused(lambda: read_drawing(BILLION_LAUGHS, "laughs.svg"))
    assert "laughs.svg, line 3" in message and "ENTITY" in message


def test_an_external_entity_is_refused_and_nothing_is_read() -> None:
    message = _refused(lambda: read_drawing(EXTERNAL, "xxe.svg"))
    assert "xxe.svg, line 2" in message and "other files" in message


def test_a_path_of_a_million_points_is_refused_before_it_is_parsed() -> None:
    points = b" L1 2" * 1_000_000
    data = (b'<svg xmlns="http://www.w3.org/2000/svg" width="10mm" height="10mm">\n'
            b'<path stroke="red" d="M0 0' + points + b'"/></svg>')
    message = _refused(lambda: read_drawing(data, "huge.svg"))
    assert "huge.svg, line 2: a path of over 500,000 points" in message


def _png_header_only(columns: int, rows: int) -> bytes:
    """A PNG whose header claims ``columns`` x ``rows`` pixels, with almost no pixel data."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", columns, rows, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(b"\0" * 1024)) + chunk(b"IEND", b""))


def test_an_image_of_100000_by_100000_pixels_is_refused_from_its_header() -> None:
    data = _png_header_only(100_000, 100_000)
    message = _refused(lambda: read_drawing(data, "bomb.png"), bound_bytes=8 << 20)
    assert "bomb.png: over the 50,000,000 pixels" in message and "10000000000" in message
    smaller = _png_header_only(8_000, 8_000)  # under Pillow's own limit, over ours
    message = _refused(lambda: read_drawing(smaller, "big.png"), bound_bytes=8 << 20)
    assert "big.png: 8,000 x 8,000 pixels, over the 50,000,000" in message


def test_a_dxf_with_an_entity_motiond_does_not_cut_is_refused_naming_it() -> None:
    doc = ezdxf.new("R2010")
    doc.modelspace().add_line((0, 0), (10, 0))
    face = doc.modelspace().add_3dface([(0, 0, 0), (1, 0, 0), (1, 1, 0)])
    stream = io.StringIO()
    doc.write(stream)
    message = _refused(lambda: read_drawing(stream.getvalue().encode(), "part.dxf"))
    assert f"part.dxf: entity 3DFACE #{face.dxf.handle} on layer '0'" in message


def test_svg_cut_short_and_an_unknown_kind_are_refused() -> None:
    cut = b'<svg xmlns="http://www.w3.org/2000/svg"><path d="M0 0 L1 1"'
    assert "not a readable SVG" in _refused(lambda: read_drawing(cut, "cut.svg"))
    assert "not a drawing motiond reads" in _refused(lambda: read_drawing(b"x", "job.pdf"))
    assert "not an image" in _refused(lambda: read_drawing(b"GIF89a", "photo.png"))


def test_text_is_not_cut_and_the_warning_says_to_convert_it() -> None:
    data = (b'<svg xmlns="http://www.w3.org/2000/svg" width="20mm" height="20mm">'
            b'<rect x="1" y="1" width="5" height="5" stroke="red" fill="none"/>'
            b'<text x="2" y="10">Hello</text></svg>')
    drawing = read_drawing(data, "label.svg")
    assert [layer.name for layer in drawing.layers] == ["#ff0000"]
    assert any("convert text to paths" in warning for warning in drawing.warnings)
