"""The host's sequence window: acks, naks, timeouts, restarts, and joining a running MCU."""

from __future__ import annotations

import pytest

from server.backends.klipper.window import SendWindow, SequenceError


def sent(window: SendWindow, count: int, now_s: float = 0.0) -> list[bytes]:
    return [window.make_block(bytes([10, i]), now_s) for i in range(count)]


def test_an_ack_releases_the_blocks_before_it_and_measures_the_round_trip() -> None:
    window = SendWindow()
    sent(window, 3)
    assert window.on_block(1, False, 0.002) == []  # a response to block 0: synced
    assert window.on_block(3, True, 0.004) == []
    assert not window.inflight and window.srtt_s is not None


def test_a_nak_resends_everything_unacknowledged_once() -> None:
    window = SendWindow()
    blocks = sent(window, 4)
    window.on_block(1, False, 0.001)  # block 0's response...
    assert window.on_block(1, True, 0.0012) == []  # ...and the ack that follows it
    assert window.on_block(1, True, 0.002) == blocks[1:]  # the same number again: a nak
    assert window.on_block(1, True, 0.0021) == [], "the naks a resend causes are not obeyed"


def test_the_ack_after_a_response_is_no_nak() -> None:
    """The firmware answers a request, then acknowledges its block with an empty block of
    the same number: with more blocks in flight (get_clock then get_config, or steps) that
    ack is no nak, and nothing is sent again."""
    window = SendWindow()
    sent(window, 3)
    for seq in (1, 2):
        assert window.on_block(seq, False, 0.001 * seq) == []  # the response
        assert window.on_block(seq, True, 0.001 * seq + 0.0002) == []  # then its ack
    assert window.retransmits == 0 and len(window.inflight) == 1


def test_a_timeout_resends_with_a_doubled_timeout() -> None:
    window = SendWindow()
    blocks = sent(window, 2)
    rto = window.rto_s
    assert window.on_timer(rto / 2) == []
    assert window.on_timer(rto + 0.001) == blocks and window.rto_s == 2 * rto


def test_a_number_never_sent_means_the_mcu_restarted() -> None:
    window = SendWindow()
    sent(window, 5)
    window.on_block(5, False, 0.001)
    sent(window, 2)
    with pytest.raises(SequenceError):
        window.on_block(0, True, 0.01)


def test_joining_an_mcu_that_served_a_host_before_adopts_its_count() -> None:
    window = SendWindow()
    first = sent(window, 1)[0]
    again = window.on_block(1, True, 0.001)  # a nak that happens to look like an ack of 0
    assert len(again) == 1 and again[0][1] == 0x10 | 1 and again[0][2:-3] == first[2:-3]
    assert window.on_block(2, False, 0.002) == [] and not window.inflight


def test_a_flood_of_empty_blocks_before_the_first_ack_draws_one_resend_per_round_trip() -> None:
    window = SendWindow()
    sent(window, 1)
    resent = [window.on_block(5, True, 0.0001 * i) for i in range(100)]  # 10 ms of naks
    assert sum(1 for blocks in resent if blocks) == 1
    assert window.on_block(5, True, 0.2)  # a round trip later: once more


def test_an_ack_read_late_releases_its_blocks_but_measures_no_round_trip() -> None:
    """Acknowledgements read at a sample (up to a tick after they arrived) are no
    measurement: the retransmission timeout stays what the timely ones made it."""
    window = SendWindow()
    sent(window, 2)
    rto_s = window.rto_s
    assert window.on_block(1, False, 0.030, timed=False) == []
    assert window.on_block(2, True, 0.031, timed=False) == []
    assert not window.inflight and window.srtt_s is None and window.rto_s == rto_s
