"""The sans-I/O line protocol: bytes in, events and reply bytes out, no event loop."""

from __future__ import annotations

from functools import reduce
from operator import xor

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.errors import ALARM_MEANINGS, CommandError, Error
from server.protocol.events import (
    Dialect,
    FramedLine,
    LineReceived,
    LineRejected,
    Realtime,
    RealtimeReceived,
    ResendError,
)
from server.protocol.lines import LineProtocol


def frame(number: int, command: str) -> bytes:
    """What printrun and OctoPrint send: ``N<number> <command>*<xor of the bytes before *>``."""
    head = f"N{number} {command}"
    return f"{head}*{reduce(xor, head.encode(), 0)}\n".encode()


def framed(number: int, text: str, *, handled: bool = False) -> LineReceived:
    return LineReceived(text, FramedLine(number, text), handled=handled)


def lines(*texts: str) -> list[LineReceived]:
    return [LineReceived(text) for text in texts]


def comparable(events: list) -> list:
    """Events with refused lines as (code, message, last line): exceptions compare by identity."""
    return [
        (e.error.code, e.error.message, getattr(e.error, "last_line", None))
        if isinstance(e, LineRejected)
        else e
        for e in events
    ]


def rejected_codes(events: list) -> list[int]:
    return [event.error.code for event in events if isinstance(event, LineRejected)]


def reprap() -> LineProtocol:
    protocol = LineProtocol()
    protocol.receive_data(b"N0 M110 N0*125\n")
    assert protocol.dialect is Dialect.REPRAP
    return protocol


# -- realtime bytes -------------------------------------------------------------------------


@pytest.mark.parametrize("command", list(Realtime))
def test_every_realtime_byte_becomes_an_event_and_no_line(command: Realtime) -> None:
    assert LineProtocol().receive_data(bytes([command])) == [RealtimeReceived(command)]


@pytest.mark.parametrize("command", [c for c in Realtime if c is not Realtime.RESET])
def test_realtime_byte_inside_a_number_is_taken_out_of_the_line(command: Realtime) -> None:
    events = LineProtocol().receive_data(b"G1 X1" + bytes([command]) + b"0\n")
    assert events == [RealtimeReceived(command), LineReceived("G1 X10")]


def test_status_query_inside_a_line_is_reported_before_the_line_completes() -> None:
    protocol = LineProtocol()
    assert protocol.receive_data(b"G1 X1?") == [RealtimeReceived(Realtime.STATUS)]
    assert protocol.receive_data(b"0\n") == lines("G1 X10")


def test_realtime_bytes_come_out_in_stream_order_with_lines() -> None:
    events = LineProtocol().receive_data(b"G0 X1\n!G0 X2\n~")
    assert events == [
        LineReceived("G0 X1"),
        RealtimeReceived(Realtime.HOLD),
        LineReceived("G0 X2"),
        RealtimeReceived(Realtime.RESUME),
    ]


def test_ctrl_x_drops_the_partial_line_at_its_place_in_the_stream() -> None:
    events = LineProtocol().receive_data(b"G1 X5\x18G0 Y1\n")
    assert events == [RealtimeReceived(Realtime.RESET), LineReceived("G0 Y1")]


def test_utf8_encoded_realtime_byte_is_a_realtime_command_even_split_between_chunks() -> None:
    protocol = LineProtocol()
    assert protocol.receive_data(b"G1 X1\xc2") == []
    assert protocol.receive_data(b"\x91\n") == [
        RealtimeReceived(Realtime.FEED_PLUS_10),
        LineReceived("G1 X1"),
    ]


def test_unknown_extended_ascii_byte_is_dropped_like_grbl_does() -> None:
    assert LineProtocol().receive_data(b"G1\x87 X1\n") == lines("G1 X1")


def test_utf8_text_in_comments_is_kept_even_where_its_bytes_look_like_realtime_bytes() -> None:
    # "á" is C3 A1 (0xA1 is mist toggle), "°" is C2 B0.
    events = LineProtocol().receive_data("G0 X1 (á 45°)\n".encode())
    assert events == lines("G0 X1 (á 45°)")


# -- line endings ---------------------------------------------------------------------------


@pytest.mark.parametrize("ending", [b"\n", b"\r", b"\r\n"])
def test_each_line_ending_style_ends_exactly_one_line(ending: bytes) -> None:
    assert LineProtocol().receive_data(b"G0 X1" + ending + b"G0 X2" + ending) == lines(
        "G0 X1", "G0 X2"
    )


def test_crlf_split_across_chunks_is_one_line_ending() -> None:
    protocol = LineProtocol()
    assert protocol.receive_data(b"G0 X1\r") == lines("G0 X1")
    assert protocol.receive_data(b"\nG0 X2\r") == lines("G0 X2")
    assert protocol.receive_data(b"\n") == []


def test_realtime_byte_between_cr_and_lf_does_not_make_an_extra_line() -> None:
    events = LineProtocol().receive_data(b"G0\r?\n")
    assert events == [LineReceived("G0"), RealtimeReceived(Realtime.STATUS)]


def test_lf_then_cr_are_two_line_endings() -> None:
    assert LineProtocol().receive_data(b"G0\n\r") == lines("G0", "")


def test_empty_and_comment_only_lines_each_give_one_line() -> None:
    events = LineProtocol().receive_data(b"\n\r\n(setup)\n; note\n   \n")
    assert events == lines("", "", "(setup)", "; note", "   ")


def test_many_lines_in_one_chunk_come_out_in_order() -> None:
    data = b"".join(f"G1 X{i}\n".encode() for i in range(500))
    assert LineProtocol().receive_data(data) == lines(*(f"G1 X{i}" for i in range(500)))


def test_one_byte_at_a_time_gives_the_same_events_as_one_chunk() -> None:
    data = b"G21\r\nG1 X1?0 F100\n\xc2\x91!(caf\xc3\xa9)\rN1 G1*99\n\x00bad\nG0 Y2~\n"
    whole = LineProtocol().receive_data(data)
    protocol = LineProtocol()
    pieces = [event for byte in data for event in protocol.receive_data(bytes([byte]))]
    assert comparable(pieces) == comparable(whole)
    assert rejected_codes(whole) == [41, 1]


_ALPHABET = list(b"G1X0 .\r\n?!~\x18\x84\x91\xa1\x87\xc2\xc3\xa9\xff\x00N*;()M5") + [0x30] * 4


@settings(max_examples=300, deadline=None)
@given(
    data=st.lists(st.sampled_from(_ALPHABET), max_size=120).map(bytes),
    cuts=st.lists(st.integers(min_value=0, max_value=120), max_size=12),
)
def test_any_chunking_of_any_byte_stream_gives_the_same_events(data: bytes, cuts: list) -> None:
    whole = LineProtocol(line_limit=10)
    expected = whole.receive_data(data)
    chunked = LineProtocol(line_limit=10)
    bounds = [0, *sorted(min(cut, len(data)) for cut in cuts), len(data)]
    events = [
        e for a, b in zip(bounds, bounds[1:], strict=False) for e in chunked.receive_data(data[a:b])
    ]
    assert merged_status(comparable(events)) == merged_status(comparable(expected))
    assert chunked.dialect is whole.dialect


class ByteByByte(LineProtocol):
    """The protocol without its whole-lines shortcut: every read scanned run by run."""

    def _take_lines(self, data: bytes, events: list) -> bool:
        return False


_MOSTLY_PLAIN = list(b"G1X0 .\r\n\n\n\nS8") + [0x30] * 4 + list(b"?\xc2\xa9\x18\x00(")


@settings(max_examples=300, deadline=None)
@given(
    data=st.lists(st.sampled_from(_MOSTLY_PLAIN), max_size=160).map(bytes),
    cuts=st.lists(st.integers(min_value=0, max_value=160), max_size=12),
)
def test_whole_lines_taken_at_once_read_exactly_as_byte_by_byte(data: bytes, cuts: list) -> None:
    """A read of plain whole lines is split in C (the raster's usual read); any chunking of
    any stream gives the same events as scanning it run by run (line ends split between
    reads, partial and overlong lines carried, a CR alone, realtime bytes)."""
    bounds = [0, *sorted(min(cut, len(data)) for cut in cuts), len(data)]
    fast, slow = LineProtocol(line_limit=10), ByteByByte(line_limit=10)
    for a, b in zip(bounds, bounds[1:], strict=False):
        assert comparable(fast.receive_data(data[a:b])) == comparable(
            slow.receive_data(data[a:b]))
    assert fast.dialect is slow.dialect


def test_a_read_of_plain_lines_ending_in_crlf_gives_one_line_each() -> None:
    protocol = LineProtocol()
    assert protocol.receive_data(b"G1 X1\r\nG1 X2\r") == lines("G1 X1", "G1 X2")
    assert protocol.receive_data(b"\nG1 X3\r\n\n") == lines("G1 X3", "")
    # a CR ended the last read; a CR LF opening this one is an empty line of its own
    assert protocol.receive_data(b"G1 X4\r") == lines("G1 X4")
    assert protocol.receive_data(b"\r\nG1 X5\n") == lines("", "G1 X5")


def merged_status(events: list) -> list:
    """Grbl's ``?`` is a flag: requests in a row before the report goes out are one request."""
    merged: list = []
    for event in events:
        if event == RealtimeReceived(Realtime.STATUS) and merged and merged[-1] == event:
            continue
        merged.append(event)
    return merged


def test_a_run_of_status_requests_in_one_chunk_is_one_request() -> None:
    events = LineProtocol().receive_data(b"?" * 4096 + b"G0 X1\n")
    assert events == [RealtimeReceived(Realtime.STATUS), *lines("G0 X1")]


# -- overflow and garbage -------------------------------------------------------------------


def test_overlong_line_is_rejected_once_and_the_next_line_is_fine() -> None:
    protocol = LineProtocol(line_limit=16)
    events = protocol.receive_data(b"G1 X" + b"1" * 40 + b"\nG0 X1\n")
    assert rejected_codes(events) == [11]
    assert events[1:] == lines("G0 X1")


def test_overlong_line_never_buffers_more_than_the_limit() -> None:
    protocol = LineProtocol(line_limit=64)
    for _ in range(1000):
        assert protocol.receive_data(b"X" * 1000) == []
        assert len(protocol._buffer) <= 64
    assert rejected_codes(protocol.receive_data(b"\n")) == [11]


def test_realtime_bytes_do_not_count_toward_the_line_length() -> None:
    protocol = LineProtocol(line_limit=8)
    events = protocol.receive_data(b"G1?? X1?0\n")
    assert events[-1] == LineReceived("G1 X10")
    assert LineProtocol(line_limit=8).receive_data(b"G1 X1234\n") == lines("G1 X1234")
    assert rejected_codes(LineProtocol(line_limit=8).receive_data(b"G1 X12345\n")) == [11]


@pytest.mark.parametrize(
    "garbage", [b"\xff\xfeG1", b"G1 \xc3(", b"\x00\x00", b"G1\x01X1", b"\x1b[A", b"\xc2\x80x"]
)
def test_garbage_line_gets_error_1_and_the_next_line_is_fine(garbage: bytes) -> None:
    events = LineProtocol().receive_data(garbage + b"\nG0 X1\n")
    assert rejected_codes(events) == [1]
    assert events[1:] == lines("G0 X1")


def test_tab_is_an_ordinary_character() -> None:
    assert LineProtocol().receive_data(b"G0\tX1\n") == lines("G0\tX1")


# -- WebSocket ------------------------------------------------------------------------------


def test_websocket_text_frame_without_newline_is_one_line() -> None:
    assert LineProtocol().receive_text("G1 X1 F100") == lines("G1 X1 F100")


def test_websocket_frame_may_hold_several_lines() -> None:
    assert LineProtocol().receive_text("G0 X1\nG0 X2\n") == lines("G0 X1", "G0 X2")
    assert LineProtocol().receive_text("G0 X1\r\nG0 X2") == lines("G0 X1", "G0 X2")


@pytest.mark.parametrize("command", list(Realtime))
def test_websocket_single_character_frame_is_a_realtime_command(command: Realtime) -> None:
    assert LineProtocol().receive_text(chr(command)) == [RealtimeReceived(command)]


def test_websocket_realtime_character_inside_a_line_is_taken_out() -> None:
    events = LineProtocol().receive_text("G1 X1\x910\u00a1")
    assert events == [
        RealtimeReceived(Realtime.FEED_PLUS_10),
        RealtimeReceived(Realtime.MIST),
        LineReceived("G1 X10"),
    ]


def test_websocket_text_keeps_non_realtime_unicode() -> None:
    assert LineProtocol().receive_text("(café 45°)") == lines("(café 45°)")


def test_websocket_empty_frame_gives_nothing_and_newline_frame_one_empty_line() -> None:
    protocol = LineProtocol()
    assert protocol.receive_text("") == []
    assert protocol.receive_text("\n") == lines("")


def test_websocket_binary_messages_are_whole_messages_too() -> None:
    protocol = LineProtocol(websocket=True)
    assert protocol.receive_data(b"G0 X1") == lines("G0 X1")
    assert protocol.receive_data(b"\xc2\x85") == [RealtimeReceived(Realtime.JOG_CANCEL)]


# -- RepRap framing -------------------------------------------------------------------------


def test_framed_line_comes_out_without_its_framing() -> None:
    events = LineProtocol().receive_data(frame(7, "G1 X5"))
    assert events == [framed(7, "G1 X5")]


def test_octoprint_first_line_sets_the_line_number_and_is_handled() -> None:
    protocol = LineProtocol()
    events = protocol.receive_data(b"N0 M110 N0*125\n")
    assert events == [framed(0, "M110 N0", handled=True)]
    assert protocol.receive_data(frame(1, "M115")) == [framed(1, "M115")]


def test_bad_checksum_asks_for_the_line_again() -> None:
    protocol = reprap()
    events = protocol.receive_data(b"N1 G1 X5*0\n")
    error = events[0].error
    assert isinstance(error, ResendError)
    assert (error.code, error.last_line) == (41, 0)
    assert protocol.reply_error(error) == (
        b"Error:checksum mismatch, Last Line: 0\r\nResend: 1\r\nok\r\n"
    )
    assert protocol.receive_data(frame(1, "G1 X5")) == [framed(1, "G1 X5")]


def test_malformed_checksum_field_is_a_checksum_error() -> None:
    assert rejected_codes(reprap().receive_data(b"N1 G1 X5*abc\n")) == [41]


def test_out_of_sequence_line_asks_for_the_missing_line_and_does_not_advance() -> None:
    protocol = reprap()
    protocol.receive_data(frame(1, "G1 X1"))
    events = protocol.receive_data(frame(3, "G1 X3") + frame(4, "G1 X4"))
    assert rejected_codes(events) == [42, 42]
    assert all(event.error.last_line == 1 for event in events)
    assert protocol.reply_error(events[0].error) == (
        b"Error:Line Number is not Last Line Number+1, Last Line: 1\r\nResend: 2\r\nok\r\n"
    )
    assert protocol.receive_data(frame(2, "G1 X2")) == [framed(2, "G1 X2")]


def test_printrun_m110_n_minus_1_restarts_numbering_at_zero() -> None:
    protocol = LineProtocol()
    protocol.receive_data(frame(5, "G1 X1"))
    events = protocol.receive_data(frame(-1, "M110") + frame(0, "G1 X2"))
    assert events == [
        framed(-1, "M110", handled=True),
        framed(0, "G1 X2"),
    ]


@pytest.mark.parametrize("m110", [b"M110 N-1\n", b"m110 n -1 ; restart\n"])
def test_unframed_m110_sets_the_last_line_number_and_is_handled(m110: bytes) -> None:
    protocol = LineProtocol()
    protocol.receive_data(frame(40, "G0 X1"))
    assert protocol.receive_data(m110) == [LineReceived(m110.decode().strip(), handled=True)]
    assert protocol.receive_data(frame(0, "G0 X2"))[0].framed == FramedLine(0, "G0 X2")


def test_framed_line_tells_whether_it_is_m110() -> None:
    assert FramedLine(0, "M110 N0").m110
    assert FramedLine(-1, "m0110").m110
    assert not FramedLine(3, "M1100").m110
    assert not FramedLine(3, "G1 X5").m110


def test_first_framed_line_sets_the_sequence() -> None:
    protocol = LineProtocol()
    assert protocol.receive_data(frame(100, "G0 X1"))[0].framed == FramedLine(100, "G0 X1")
    assert rejected_codes(protocol.receive_data(frame(100, "G0 X1"))) == [42]


def test_garbled_framed_line_is_answered_with_a_resend_request() -> None:
    protocol = reprap()
    events = protocol.receive_data(b"N1 G1 X\xff5*12\n")
    assert rejected_codes(events) == [41]
    assert b"Resend: 1" in protocol.reply_error(events[0].error)


def test_unframed_n_word_is_a_grbl_line_number_left_to_the_parser() -> None:
    assert LineProtocol().receive_data(b"N10 G1 X5\n") == lines("N10 G1 X5")


# -- dialects -------------------------------------------------------------------------------


def test_grbl_sender_stays_in_the_grbl_dialect() -> None:
    protocol = LineProtocol()
    protocol.receive_data(b"\x18?$$\n$#\nM105\n")
    assert protocol.dialect is Dialect.GRBL
    refused = CommandError(Error.UNSUPPORTED, "unsupported M105")
    assert protocol.reply_error(refused) == b"error:20\r\n"


@pytest.mark.parametrize(
    "first_lines",
    [b"M105\n", frame(-1, "M110") + frame(0, "M105"), b"N0 M110 N0*125\n", b"(hi)\nM115\n"],
    ids=["printrun-polling", "printrun-print", "octoprint", "comment-then-m115"],
)
def test_reprap_hosts_are_recognised_by_their_first_lines(first_lines: bytes) -> None:
    protocol = LineProtocol()
    protocol.receive_data(first_lines)
    assert protocol.dialect is Dialect.REPRAP
    assert protocol.banner() == b"start\r\n"


def test_the_dialect_is_decided_once() -> None:
    protocol = LineProtocol()
    protocol.receive_data(b"G21\nM105\n")
    assert protocol.dialect is Dialect.GRBL


def test_fixed_dialects_are_never_switched() -> None:
    grbl = LineProtocol(dialect="grbl")
    grbl.receive_data(b"N0 M110 N0*125\n")
    assert grbl.dialect is Dialect.GRBL
    assert LineProtocol(dialect="reprap").dialect is Dialect.REPRAP
    with pytest.raises(ValueError):
        LineProtocol(dialect="marlin")


def test_in_reprap_dialect_ascii_realtime_characters_are_ordinary_text() -> None:
    protocol = reprap()
    events = protocol.receive_data(b"M117 Done! Ready?\n" + frame(1, "M117 Hi~!"))
    assert events == [
        LineReceived("M117 Done! Ready?"),
        framed(1, "M117 Hi~!"),
    ]
    assert protocol.receive_data(b"\x18\x85") == [
        RealtimeReceived(Realtime.RESET),
        RealtimeReceived(Realtime.JOG_CANCEL),
    ]


def test_reset_drops_the_partial_line_and_keeps_dialect_and_numbering() -> None:
    protocol = reprap()
    protocol.receive_data(b"G1 X")
    protocol.reset()
    assert protocol.dialect is Dialect.REPRAP
    assert protocol.receive_data(frame(1, "G0 Y1")) == [framed(1, "G0 Y1")]


# -- replies --------------------------------------------------------------------------------


def test_grbl_banner_is_exact() -> None:
    assert LineProtocol().banner() == b"\r\nGrbl 1.1h ['$' for help]\r\n"


def test_reply_ok_puts_message_lines_before_ok() -> None:
    protocol = LineProtocol()
    assert protocol.reply_ok() == b"ok\r\n"
    assert protocol.reply_ok(["$0=10", "$1=25"]) == b"$0=10\r\n$1=25\r\nok\r\n"


def test_ok_suffix_rides_on_the_ok_line_only_in_reprap() -> None:
    assert reprap().reply_ok(ok_suffix="T:0.0 /0.0 B:0.0 /0.0") == b"ok T:0.0 /0.0 B:0.0 /0.0\r\n"
    assert LineProtocol().reply_ok(ok_suffix="C: X:0.0000") == b"C: X:0.0000\r\nok\r\n"


@pytest.mark.parametrize("messages", [["two\nlines"], ["ok"], ["ok T:0", "then more"]])
def test_reply_messages_must_be_single_lines_that_do_not_read_as_ok(messages: list[str]) -> None:
    with pytest.raises(ValueError):
        LineProtocol().reply_ok(messages)


def test_a_last_message_starting_ok_is_the_ok_lines_suffix_marlins_m105() -> None:
    assert reprap().reply_ok(["ok T:0.0 /0.0"]) == b"ok T:0.0 /0.0\r\n"
    assert LineProtocol().reply_ok(["ok T:0.0 /0.0"]) == b"T:0.0 /0.0\r\nok\r\n"


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (CommandError(Error.UNSUPPORTED, "G81"), b'echo:Unknown command: "G81"\r\nok\r\n'),
        (CommandError(Error.UNKNOWN_COMMAND, "frobnicate"),
         b'echo:Unknown command: "frobnicate"\r\nok\r\n'),
        (CommandError(22), b"echo:Undefined feed rate (code 22)\r\nok\r\n"),
        (CommandError(Error.INVALID_TARGET, "arc\nend"), b"echo:arc end (code 33)\r\nok\r\n"),
        (CommandError(9, "G-code locked out during ALARM:40 (Halt): $X or M999 to unlock"),
         b"//action:notification G-code locked out during ALARM:40 (Halt): $X or M999 to unlock"
         b"\r\necho:G-code locked out during ALARM:40 (Halt): $X or M999 to unlock (code 9)"
         b"\r\nok\r\n"),  # OctoPrint keeps the connection and shows the notification
        (CommandError(Error.LINE_OVERFLOW, "too long"), b"echo:too long (code 11)\r\nok\r\n"),
        (CommandError(Error.SOFT_LIMIT, "X500 beyond 400"),
         b"echo:X500 beyond 400 (code 40)\r\nok\r\n"),  # Marlin clamps: no firmware fault
    ],
)
def test_reprap_errors_are_worded_like_marlin(error: CommandError, expected: bytes) -> None:
    assert reprap().reply_error(error) == expected


def test_a_reprap_host_is_notified_of_an_alarm_and_of_the_unlock() -> None:
    assert reprap().push("ALARM:40").decode().splitlines() == [
        "ALARM:40", "//action:notification ALARM:40 (" + ALARM_MEANINGS[40] + "): M999 to unlock"]
    assert reprap().push("[MSG:Caution: Unlocked]").decode().splitlines() == [
        "[MSG:Caution: Unlocked]", "//action:notification Unlocked"]
    assert LineProtocol().push("ALARM:40") == b"ALARM:40\r\n"


def test_reprap_error_replies_never_use_grbl_error_prefix_and_always_end_with_ok() -> None:
    protocol = reprap()
    for code in Error:
        reply = protocol.reply_error(CommandError(code, "x"))
        assert not reply.lower().startswith(b"error:") or reply.startswith(b"Error:")
        assert reply.endswith(b"\r\nok\r\n")
        assert b"error:" not in reply


def test_plain_checksum_error_from_the_parser_asks_to_resend_the_next_line() -> None:
    protocol = reprap()
    assert protocol.reply_error(CommandError(41)).endswith(b"Resend: 1\r\nok\r\n")


@pytest.mark.parametrize(
    "message", ["<Idle|MPos:0.000,0.000,0.000|FS:0,0>", "ALARM:1", "[MSG:Looks ok]", "[GC:G0]"]
)
def test_push_adds_a_line_ending(message: str) -> None:
    assert LineProtocol().push(message) == message.encode() + b"\r\n"


@pytest.mark.parametrize(
    "message",
    ["ok", "Broken probe", "[MSG:x] ok", "[VER:1.1h.x:]", "[OPT:V,15,128]", "[HLP:$$]", "a\nb"],
)
def test_push_refuses_what_a_sender_would_read_as_a_reply(message: str) -> None:
    with pytest.raises(ValueError):
        LineProtocol().push(message)
