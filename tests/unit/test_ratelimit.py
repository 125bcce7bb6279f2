"""The token bucket that paces status reports and the input of connections without control."""

from __future__ import annotations

import pytest

from server.runtime.ratelimit import TokenBucket


def test_amounts_are_taken_whole_or_not_at_all_and_the_wait_says_when() -> None:
    bucket = TokenBucket(rate_per_s=1000.0, burst=1024.0, now_s=0.0)
    assert bucket.take(0.0, 1000) == 0.0
    assert bucket.take(0.0, 256) == pytest.approx(0.232)  # 24 left: 232 more at 1000/s
    assert bucket.wait_s(0.232, 256) == pytest.approx(0.0)
    assert bucket.take(0.232, 256) == 0.0
    assert bucket.take(0.232, 1) == pytest.approx(0.001)


def test_more_than_the_burst_waits_only_for_a_full_bucket() -> None:
    bucket = TokenBucket(rate_per_s=100.0, burst=10.0, now_s=0.0)
    assert bucket.take(0.0, 4096) == 0.0  # capped at the burst, so it can never wait forever
    assert bucket.take(0.0, 4096) == pytest.approx(0.1)
