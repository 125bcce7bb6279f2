"""What realtime bytes cost before they are examined: counted in C, cut into bounded slices,
paid from an allowance that may be overspent by the slice just examined."""

from __future__ import annotations

import pytest

from server.runtime.ratelimit import Allowance
from server.sessions.input import RESET_COST, SLICE_COST, affordable, realtime_cost


def test_realtime_cost_counts_the_bytes_the_protocol_reads_one_at_a_time() -> None:
    assert realtime_cost(b"G1 X10 Y20 F3000\r\n") == 0
    assert realtime_cost(b"!~?") == 3
    assert realtime_cost(b"?" * 4096) == 1 and realtime_cost(b"??!??") == 3  # a run: one read
    assert realtime_cost(b"\x91\xc3\xa9") == 3  # an override, and UTF-8 text (refunded later)
    assert realtime_cost(b"\x18") == RESET_COST


@pytest.mark.parametrize("data", [b"!" * 4096, b"!A~B\x91" * 800, b"\x18\x85!" * 1000,
                                  b"G1 X1\n" * 700 + b"!" * 100, b"\xc3!" * 2048])
def test_a_flood_is_cut_into_slices_of_bounded_cost(data: bytes) -> None:
    slices = []
    while data:
        size = affordable(data, SLICE_COST)
        slices.append(data[:size])
        data = data[size:]
    assert all(realtime_cost(piece) <= SLICE_COST or len(piece) == 1 for piece in slices)
    assert all(realtime_cost(piece + rest[:1]) > SLICE_COST
               for piece, rest in zip(slices, slices[1:], strict=False)), "as long as allowed"


def test_lines_without_realtime_bytes_are_taken_whole() -> None:
    data = b"G1 X1 Y2\n" * 455
    assert affordable(data, SLICE_COST) == len(data)


def test_an_allowance_may_be_overspent_and_then_waits_until_it_is_above_zero() -> None:
    allowance = Allowance(rate_per_s=100.0, burst=50.0, now_s=0.0)
    assert allowance.wait_s(0.0) == 0.0
    allowance.spend(0.0, 80.0)
    assert allowance.level(0.0) == pytest.approx(-30.0)
    assert allowance.wait_s(0.0) == pytest.approx(0.31)
    assert allowance.wait_s(0.31) == 0.0
    assert allowance.level(10.0) == 50.0, "refilled up to its burst, no more"
