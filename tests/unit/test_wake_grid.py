"""Periodic wake-ups of an idle server fall on one grid of whole periods (monotonic time), so
that the loop monitor's, the kernel's second and a Klipper MCU's clock polls share wake-ups."""

from __future__ import annotations

import pytest

from server.runtime.clock import on_grid_s


def test_the_next_wake_up_is_the_first_whole_multiple_of_the_period_after_now() -> None:
    assert on_grid_s(100.005, 0.5) == pytest.approx(100.5)
    assert on_grid_s(100.5, 0.5) == pytest.approx(101.0)  # never now itself
    assert on_grid_s(99.99, 1.0) == pytest.approx(100.0)


def test_periods_that_divide_each_other_share_their_wake_ups() -> None:
    """A monitor every 0.5 s and a second every 1 s: each second's wake-up is one of the
    monitor's, whatever time each started at."""
    for start_s in (3.1, 7.77, 12.5):
        monitor_s = {round(on_grid_s(start_s + k * 0.5, 0.5), 9) for k in range(20)}
        seconds = {round(on_grid_s(start_s + k, 1.0), 9) for k in range(8)}
        assert seconds <= monitor_s
