"""The sans-I/O Grbl link core: character counting, in-order reply matching, report parsing."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from server.backends.grbl import link as link_module
from server.backends.grbl import reports as reports_module
from server.backends.grbl.link import (
    AlarmReport,
    Answered,
    Banner,
    Feedback,
    Link,
    StatusReport,
    adopted_numbers,
    compact,
    mismatches,
    parse_settings,
)
from server.backends.grbl.reports import parse_status

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"


def connected(buffer_bytes: int = 127) -> Link:
    link = Link(buffer_bytes)
    events = link.receive(BANNER)
    assert events == [Banner("Grbl 1.1h ['$' for help]", ())]
    return link


def test_nothing_is_sent_before_the_banner() -> None:
    link = Link()
    assert not link.fits(4)
    with pytest.raises(RuntimeError):
        link.send("G0")
    link.receive(b"GrblHAL 1.1f ['$' or '$HELP' for help]\n")
    assert link.fits(4)


def test_character_counting_holds_the_bytes_of_unanswered_lines_under_the_buffer() -> None:
    link = connected(20)
    token_a, data_a = link.send("G1X10Y10")  # 9 bytes with the newline
    assert data_a == b"G1X10Y10\n"
    token_b, _ = link.send("G1X20Y20")  # 18
    assert link.used_bytes == 18
    assert not link.fits(3)  # 21 > 20
    assert link.fits(2)
    assert link.receive(b"ok\r\n") == [Answered(token_a, (), None)]
    assert link.used_bytes == 9 and link.fits(11) and not link.fits(12)
    assert link.receive(b"ok\n") == [Answered(token_b, (), None)]
    assert link.used_bytes == 0 and link.in_flight == 0


def test_a_line_longer_than_the_buffer_goes_alone() -> None:
    link = connected(16)
    assert link.fits(40)
    link.send("X" * 39)
    assert not link.fits(2)


def test_answers_match_lines_in_order_with_the_lines_printed_before_them() -> None:
    link = connected()
    first, _ = link.send("$#")
    second, _ = link.send("G1X")
    third, _ = link.send("G38.2Z-5F100")
    events = link.receive(b"[G54:0.000,0.000]\r\n[G55:1.000,0.000]\r\nok\r\nerr")
    assert events == [Answered(first, ("[G54:0.000,0.000]", "[G55:1.000,0.000]"), None)]
    events = link.receive(b"or:26\r\n[PRB:0.000,0.000,-2.000:1]\r\nok\r\n")
    assert events == [Answered(second, (), 26),
                      Answered(third, ("[PRB:0.000,0.000,-2.000:1]",), None)]


def test_grblhal_lines_end_crlf_and_an_errors_clearing_ok_answers_nothing() -> None:
    """grblHAL's sticky errors (its rig: ``G1 X1e3\\r\\n`` is ``error:N`` then ``ok``, the
    ``\\n`` clearing it; a ``$`` line needs an empty line of its own): the lines behind an
    error are answered by their own replies."""
    link = connected()
    link.use_grblhal()
    bad, data = link.send("G1X1e3")
    assert data == b"G1X1e3\r\n"
    good, _ = link.send("G0X1")
    setting, data = link.send("$99=1")
    assert data == b"$99=1\r\n\r\n"
    query, _ = link.send("$22")
    events = link.receive(b"error:36\r\nok\r\nok\r\nerror:53\r\nok\r\n$22=0\r\nok\r\nok\r\n")
    assert events == [Answered(bad, (), 36), Answered(good, (), None),
                      Answered(setting, (), 53), Answered(query, ("$22=0",), None)]
    assert link.in_flight == 0 and link.used_bytes == 0
    link.lost()
    link.receive(BANNER)
    assert link.send("G0X1")[1] == b"G0X1\n", "a board connected anew says what it is"


def test_status_alarm_and_feedback_are_not_answers() -> None:
    link = connected()
    token, _ = link.send("G0X1")
    events = link.receive(b"<Run|MPos:1.000,2.000,3.000|FS:500,0>\r\nALARM:2\r\nok\r\n")
    assert isinstance(events[0], StatusReport)
    assert events[1:] == [AlarmReport(2), Answered(token, (), None)]
    assert link.receive(b"[MSG:Pgm End]\n") == [Feedback("[MSG:Pgm End]")]


def test_a_reset_drops_unanswered_lines_and_ignores_answers_until_the_banner() -> None:
    link = connected()
    tokens = [link.send("G1X1")[0], link.send("G1X2")[0]]
    assert link.reset() == tokens
    assert not link.fits(2)
    # an ok already on the wire when Ctrl-X was sent must not answer a later line
    assert link.receive(b"ok\r\n") == [Feedback("ok")]
    link.receive(BANNER)
    token, _ = link.send("G1X3")
    assert link.receive(b"ok\n") == [Answered(token, (), None)]


def test_a_controller_that_restarts_by_itself_drops_what_it_had() -> None:
    link = connected()
    token, _ = link.send("G1X1")
    events = link.receive(BANNER)
    assert events == [Banner("Grbl 1.1h ['$' for help]", (token,))]
    assert link.in_flight == 0 and link.used_bytes == 0


def test_a_lost_connection_drops_everything_and_a_partial_line() -> None:
    link = connected()
    token, _ = link.send("G1X1")
    link.receive(b"o")
    assert link.lost() == [token]
    link.receive(BANNER)
    link.send("G1X2")
    assert link.receive(b"k\n") == []  # not an "ok": the half before the loss is gone
    assert link.in_flight == 1


def test_junk_without_newline_is_bounded() -> None:
    link = connected()
    link.receive(b"x" * 5000)
    token, _ = link.send("G0X1")
    assert link.receive(b"\nok\n") == [Answered(token, (), None)]


def test_a_garbled_or_non_finite_status_report_is_dropped_and_the_link_goes_on() -> None:
    link = connected()
    token, _ = link.send("G0X1")
    noisy = b"<Run|MPos:1.0,x2,3|FS:0,0>\n<Run|MPos:nan,0,0>\n<Idle|Bf:1e999,0>\n"
    assert link.receive(noisy + b"ok\n") == [Answered(token, (), None)]
    assert link.garbled_reports == 3
    (report,) = link.receive(b"<Idle|MPos:4.000,5.000,6.000>\n")
    assert isinstance(report, StatusReport) and report.status.machine_mm == (4.0, 5.0, 6.0)


def test_status_report_fields() -> None:
    status = parse_status(
        "<Hold:1|MPos:1.000,-2.500,3.000|Bf:15,128|Ln:42|FS:1200,300|Pn:XZ|WCO:1.000,0,0|"
        "Ov:110,100,90|A:SF>")
    assert status.state == "Hold:1" and status.base_state == "Hold"
    assert status.machine_mm == (1.0, -2.5, 3.0)
    assert (status.planner_free_blocks, status.rx_free_bytes) == (15, 128)
    assert status.line_number == 42 and status.feed_mm_min == 1200 and status.spindle_s == 300
    assert status.pins == "XZ" and status.wco_mm == (1.0, 0.0, 0.0)
    assert status.overrides == (110, 100, 90) and status.accessories == "SF"


def test_work_position_reports_use_the_last_offset_seen() -> None:
    link = connected()
    link.receive(b"<Idle|WPos:0.000,0.000|FS:0,0|WCO:10.000,5.000>\n")
    (event,) = link.receive(b"<Idle|WPos:1.000,1.000|F:0>\n")
    assert isinstance(event, StatusReport)
    assert event.status.machine_mm == (11.0, 6.0) and event.status.wco_mm is None


def test_compact_drops_comments_and_spaces() -> None:
    assert compact("G1 X10 (go) Y 2 ; done") == "G1X10Y2"
    assert compact("$J=G91 X1 F100") == "$J=G91X1F100"


def test_settings_and_their_mismatches() -> None:
    settings = parse_settings(["$100=250.000", "$110=500.000", "$32=1", "[MSG:x]", "$N0="])
    assert settings == {100: 250.0, 110: 500.0, 32: 1.0}
    numbers = adopted_numbers(2)
    assert numbers == [11, 32, 100, 101, 110, 111, 120, 121, 130, 131]
    ours = {100: 80.0, 110: 500.0004, 32: 1, 11: 0.01}
    assert mismatches(settings, ours, numbers) == [(100, 80.0, 250.0)]


@pytest.mark.parametrize("module", [link_module, reports_module])
def test_the_link_core_does_no_io(module: object) -> None:
    tree = ast.parse(Path(module.__file__).read_text())  # type: ignore[attr-defined]
    names = {alias.name for node in ast.walk(tree)
             if isinstance(node, ast.Import | ast.ImportFrom)
             for alias in (node.names if isinstance(node, ast.Import) else
                           [ast.alias(node.module or "")])}
    assert not {name.split(".")[0] for name in names} & {
        "asyncio", "socket", "serial", "serial_asyncio"}
    ours = {name for name in names if name.startswith("server")}
    assert ours <= {"server.backends.grbl.reports"}, "only the link's own report parser"
