"""[klippy_api]'s bounds, pure: framing in linear time, hostile JSON as an error item (not a
dropped connection), numbers and lines of Klipper's G-code within bounds."""

from __future__ import annotations

import time

import pytest

from modules.klippy_api import wire
from modules.klippy_api.gcode import translate
from server.errors import CommandError

MIB = 1 << 20


def test_framer_takes_a_mebibyte_in_reads_of_256_bytes_in_linear_time() -> None:
    body = wire.encode({"id": 1, "method": "gcode/script",
                        "params": {"script": "G1 X1\n" * (MIB // 9)}})
    framer = wire.Framer()
    start_s = time.perf_counter()
    items = [framer.feed(body[i: i + 256]) for i in range(0, len(body), 256)]
    elapsed_s = time.perf_counter() - start_s
    assert [item for batch in items for item in batch] == [wire.parse_request(body[:-1])]
    assert elapsed_s < 0.1  # 12 ms here; searching the whole buffer at each read: 600 ms


def test_framer_gives_one_request_at_a_time() -> None:
    framer = wire.Framer()
    framer.push(wire.encode({"id": 1, "method": "info"}) + b" \x03" +
                wire.encode({"id": 2, "method": "info"}) + b'{"id"')
    first, second = framer.pop(), framer.pop()
    assert isinstance(first, wire.Request) and isinstance(second, wire.Request)
    assert (first.id, second.id, framer.pop()) == (1, 2, None)
    assert framer.feed(b': 3, "method": "info"}\x03') == [wire.Request(3, "info")]


@pytest.mark.parametrize(("text", "request_id", "reason"), [
    (b'{"id": NaN, "method": "info"}', None, "finite"),
    (b'{"id": -Infinity, "method": "info"}', None, "finite"),
    (b'{"id": 1e999, "method": "info"}', None, "finite"),
    (b'{"id": 12345678901234567890, "method": "info"}', None, "digits"),
    (b'{"id": 4, "method": "info", "params": {"a": [1e400]}}', 4, "finite"),
    (b'{"id": {"a": 1}, "method": "info"}', None, "'id'"),
    (b'{"id": 5, "method": 4}', 5, "method"),
    (b'{"id": 6, "method": "info", "params": [1]}', 6, "params"),
    (b'{"id": 7, "method": "info", "params": {"a": ' + b"[" * 5000 + b"]" * 5000 + b"}}", 7,
     "nested"),
    (b'{"id": "x7", "params": ' + b"{\"a\":" * 5000 + b"1" + b"}" * 5001, "x7", "nested"),
])
def test_a_hostile_request_is_an_item_to_answer_with_an_error(
        text: bytes, request_id: object, reason: str) -> None:
    item = wire.parse_request(text)
    assert isinstance(item, wire.Malformed)
    assert item.id == request_id and reason in item.message, item


def test_ids_and_numbers_that_json_carries_back_are_kept() -> None:
    item = wire.parse_request(b'{"id": -9223372036854775807, "method": "m", '
                              b'"params": {"f": 1.5e300, "s": "NaN"}}')
    assert item == wire.Request(-9223372036854775807, "m", {"f": 1.5e300, "s": "NaN"})


@pytest.mark.parametrize(("script", "reason"), [
    ("SET_VELOCITY_FACTOR FACTOR=1e308", "FACTOR"),
    ("SET_VELOCITY_FACTOR FACTOR=0", "FACTOR must be positive"),
    ("M220 S" + "9" * 200, "S must be"),
    ("_CLIENT_LINEAR_MOVE X=1e10", "X must be"),
    ("SET_GCODE_OFFSET Z_ADJUST=-1e300", "Z_ADJUST must be"),
    ("G91\nG1 X" + "9" * 200 + "\nG90", "X must be"),
    ("M117 " + "x" * 300, "longer than 256"),
])
def test_numbers_and_lines_beyond_their_bounds_are_refused(script: str, reason: str) -> None:
    with pytest.raises(CommandError, match=reason):
        translate(script, 6000.0)
