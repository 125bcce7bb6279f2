"""Held-back input keeps WebSocket message ends, and its realtime bytes are found at once."""

from __future__ import annotations

from server.protocol.events import LineReceived, Realtime, RealtimeReceived
from server.protocol.lines import LineProtocol
from server.runtime.backlog import Backlog


def test_held_websocket_messages_come_back_with_their_ends_and_realtime_is_seen_at_once() -> None:
    protocol = LineProtocol(websocket=True)
    backlog = Backlog(1 << 20)
    seen = backlog.hold(protocol, b"G0 X1", final=True) + backlog.hold(protocol, b"!G0", False)
    seen += backlog.hold(protocol, b" X2", final=True)
    assert seen[1] == RealtimeReceived(Realtime.HOLD)
    lines = []
    while backlog:
        piece, final = backlog.take(4)
        lines += [e.text for e in protocol.receive_data(piece, final=final)
                  if isinstance(e, LineReceived)]
    assert lines == ["G0 X1", "G0 X2"]  # each message's end ended its line, no line more


def test_byte_stream_input_is_one_segment_and_ends_no_line() -> None:
    protocol = LineProtocol()
    backlog = Backlog(1 << 20)
    backlog.hold(protocol, b"G0 X1\nG0")
    backlog.hold(protocol, b" X2")
    assert backlog.take(100) == (b"G0 X1\nG0 X2", False)
    assert len(backlog) == 0
