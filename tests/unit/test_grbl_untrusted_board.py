"""A board is untrusted input: strict report parsing, bounded capture, clean and rate-limited
pushes (the pure cores: reports, link, feedback gate)."""

from __future__ import annotations

import pytest

from server.backends.grbl.feedback import FeedbackGate, clean_line, clean_reply
from server.backends.grbl.link import (
    MAX_MESSAGES_PER_LINE,
    Answered,
    Link,
    StatusReport,
    parse_build_options,
)
from server.backends.grbl.reports import parse_status

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"


def connected() -> Link:
    link = Link(127)
    link.receive(BANNER)
    return link


@pytest.mark.parametrize("report", [
    "<Run\x0b|MPos:0.000,0.000,0.000|FS:0,0>",  # a noise byte in the state
    "<Runn|MPos:0.000,0.000,0.000>",
    "<Idle|MPos:1e308,0,0>",
    "<Idle|MPos:1000001,0,0>",
    "<Idle|MPos:1,2,3,4,5,6,7>",
    "<Idle|MPos:1,,3>",
    "<Idle|MPos:0,0,0|Ov:1000000000000,100,100>",
    "<Idle|MPos:0,0,0|Ov:100,200,100>",
    "<Idle|MPos:0,0,0|Bf:-1,99999999999>",
    "<Idle|MPos:0,0,0|Bf:15,70000>",
    "<Idle|MPos:0,0,0|Bf:15>",
    "<Idle|MPos:0,0,0|FS:-5,0>",
    "<Idle|MPos:0,0,0|Ln:-3>",
    "<Idle|MPos:0,0,0|Pn:X?>",
    "<Idle|MPos:0,0,0|MPos:1,1,1>",
    "<Idle|MPos:0,0,0|FS:0,0>>",
    "<Idle|MPos:0x10,0,0>",
])
def test_a_report_a_healthy_board_never_sends_is_refused(report: str) -> None:
    with pytest.raises(ValueError):
        parse_status(report)


def test_every_state_grbl_defines_and_unknown_fields_are_accepted() -> None:
    for state in ("Idle", "Run", "Hold:0", "Hold:1", "Jog", "Home", "Alarm", "Check",
                  "Door:0", "Door:3", "Sleep"):
        assert parse_status(f"<{state}|MPos:0.000,0.000,0.000|FS:0,0>").state == state
    status = parse_status("<Idle|MPos:-199.5,0,0|Bf:15,127|FS:0,0|SD:4.5,x|Ov:100,25,10>")
    assert status.machine_mm == (-199.5, 0.0, 0.0) and status.rx_free_bytes == 127
    assert status.overrides == (100, 25, 10)


def test_noisy_reports_are_counted_and_dropped_and_the_session_goes_on() -> None:
    link = connected()
    token, _ = link.send("G0X1")
    noise = b"<Run\x0b|MPos:0,0,0>\n<Idle|MPos:1e308,0,0>\n<Idle|Bf:-1,99999999999>\n"
    assert link.receive(noise + b"ok\n") == [Answered(token, (), None)]
    assert link.garbled_reports == 3
    (event,) = link.receive(b"<Idle|MPos:1.000,2.000,3.000|FS:0,0>\r\n")
    assert isinstance(event, StatusReport)


def test_lines_kept_for_a_line_in_flight_are_bounded_and_counted() -> None:
    link = connected()
    token, _ = link.send("$$")
    flood = b"".join(b"[MSG:chatter %d]\r\n" % n for n in range(20_000))
    assert link.receive(flood) == []
    (answer,) = link.receive(b"ok\r\n")
    assert isinstance(answer, Answered) and answer.token == token
    assert len(answer.messages) == MAX_MESSAGES_PER_LINE + 1
    assert answer.messages[-1] == f"[MSG:{20_000 - MAX_MESSAGES_PER_LINE} more lines from " \
        "the controller]"
    assert link.dropped_lines == 20_000 - MAX_MESSAGES_PER_LINE


def test_a_line_too_long_is_dropped_whole_even_split_across_reads() -> None:
    link = connected()
    token, _ = link.send("G0X1")
    link.receive(b"x" * 3000)
    link.receive(b"ok-looking tail\nok\n")
    assert link.dropped_lines == 1
    assert link.in_flight == 0, "the answer after the junk line still counts"
    del token


def test_the_receive_buffer_from_dollar_i() -> None:
    assert parse_build_options(["[VER:1.1h.20190830:]", "[OPT:V,15,128]"]) == (15, 128)
    assert parse_build_options(["[VER:x]"]) is None


def test_pushed_lines_are_printable_bounded_and_never_read_as_a_reply() -> None:
    assert clean_line("[MSG:Pgm End]") == "[MSG:Pgm End]"
    assert clean_line("[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]").startswith("[GC:G0")
    assert clean_line("ok\x07") == "[MSG:controller: ok]"
    assert clean_line("[VER:1.1h]") == "[MSG:controller: (VER:1.1h)]"
    assert clean_line("[GC:ok]") == "[MSG:controller: (GC:ok)]"
    assert len(clean_line("x" * 10_000)) < 250
    assert clean_reply("$100=250.000") == "$100=250.000"
    assert clean_reply("ok") == "[MSG:controller: ok]"


def test_the_gate_passes_a_burst_then_one_summary_per_period() -> None:
    gate = FeedbackGate(0.0, rate_per_s=10, burst=5)
    shown = [line for n in range(1000) for line in gate.offer(f"[MSG:{n}]", 0.001 * n)]
    assert shown[:5] == [f"[MSG:{n}]" for n in range(5)]
    assert len(shown) <= 5 + 2 * 10  # a second of flood: the burst, then summaries and lines
    assert any("more lines not shown" in line for line in shown)
    later = gate.flush(10.0)
    assert later == [] or "more lines not shown" in later[0]
    assert gate.held_back == 0
