"""[klippy_api]'s bounds, pure: framing in linear time, hostile JSON as an error item (not a
dropped connection), the loop budget's stretches on a fake clock, the scripts' byte budget,
and long scripts cut into pieces and searched for M112 as every line would be."""

from __future__ import annotations

import time

import pytest

from modules.klippy_api import gcode, wire
from modules.klippy_api.budget import ByteBudget, LoopBudget
from modules.klippy_api.gcode import FeedOverride, Line, translate
from server.errors import CommandError
from server.kernel.control import halts_at_once

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


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s


def test_loop_budget_lets_work_run_for_a_burst_then_pauses_for_its_share() -> None:
    clock = FakeClock()
    budget = LoopBudget(burst_s=0.002, share=0.25, clock=clock)
    assert budget.may_work()
    clock.now_s += 0.0019
    assert budget.may_work()  # within the burst
    clock.now_s += 0.0002
    assert not budget.may_work()  # 2.1 ms ran: 6.3 ms of pause for a quarter of the loop
    assert budget.wait_s() == pytest.approx(0.0063)
    clock.now_s += 0.006
    assert not budget.may_work()
    clock.now_s += 0.0004
    assert budget.may_work()


def test_loop_budget_owes_nothing_when_the_loop_turned_within_the_burst() -> None:
    clock = FakeClock()
    budget = LoopBudget(burst_s=0.002, share=0.5, clock=clock)
    for _ in range(100):  # many short stretches, each ended by the loop turning
        assert budget.may_work()
        clock.now_s += 0.0015
        budget.end_stretch(budget._stretch)
        clock.now_s += 0.0001
    budget.end_stretch(budget._stretch - 1)  # a late end of an old stretch changes nothing
    assert budget.wait_s() == 0.0


def test_byte_budget_refuses_what_does_not_fit_and_takes_back_what_is_given() -> None:
    budget = ByteBudget(10)
    assert budget.take(6) and not budget.take(5) and budget.take(4)
    budget.give(6)
    assert budget.used_bytes == 4 and budget.take(6)


@pytest.mark.parametrize("line", [
    "M112", "m112", " M112 ", "N10 M112", "N5M112", "M 112", "M0112", "M112 ; stop", "M112X1",
    "M1120", "M11", "G1 M112", "; M112", "XM112", "M112.5", "N M112", "M\t112",
])
def test_stops_at_once_finds_a_line_as_halts_at_once_does(line: str) -> None:
    script = f"G1 X1\n{line}\nG1 X2"
    assert gcode.stops_at_once(script) is halts_at_once(line.strip())
    assert gcode.stops_at_once(line) is halts_at_once(line.strip())


def test_a_long_script_is_cut_at_line_ends_into_pieces_that_translate_alike() -> None:
    script = "".join(f"G1 X{i} F3000\nM220 S{50 + i % 100}\n" for i in range(2000))
    pieces = list(gcode.pieces(script, 4096))
    assert "".join(pieces) == script and len(pieces) > 10
    assert all(piece.endswith("\n") for piece in pieces)
    steps = [step for piece in pieces for step in gcode.translate_piece(piece, 6000.0)]
    assert steps == translate(script, 6000.0)
    assert steps[:2] == [Line("G1 X0 F3000"), FeedOverride(50)]


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
