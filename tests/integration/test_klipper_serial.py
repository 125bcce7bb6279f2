"""The Klipper link opens a real tty at Klipper's usual rates, 250000 baud included."""

from __future__ import annotations

import array
import fcntl
import os
import pty

import pytest

from server.backends.klipper.link import open_serial

TCGETS2 = 0x802C542A  # Linux: struct termios2, whose speeds are plain numbers (any rate)


def speeds_of(fd: int) -> tuple[int, int]:
    termios2 = array.array("i", [0] * 16)
    fcntl.ioctl(fd, TCGETS2, termios2)
    return termios2[9], termios2[10]  # c_ispeed, c_ospeed after the flags, line and c_cc


@pytest.mark.parametrize("baud", [115200, 250000])
def test_the_device_runs_at_the_configured_rate_and_does_not_block(baud: int) -> None:
    master, slave = pty.openpty()
    try:
        fd = open_serial(os.ttyname(slave), baud)
        try:
            assert speeds_of(fd) == (baud, baud)  # 250000 has no termios constant
            assert not os.get_blocking(fd)
        finally:
            os.close(fd)
    finally:
        os.close(master)
        os.close(slave)
