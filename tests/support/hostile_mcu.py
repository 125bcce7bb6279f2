"""A scripted misbehaving Klipper MCU: the virtual MCU on a pty, with the faults of a broken or
hostile board (issue #21, point 5), each one a method:

- :meth:`HostileMcu.noise` ``"garbage"``: its transmit line sends random bytes, no block;
  ``"flood"``: well-formed ``stats`` messages as fast as the host reads them, none of which
  acknowledges a host block. Either way it answers nothing, but still hears and obeys what the
  host sends (so an ``emergency_stop`` reaches it); ``None`` ends the fault.
- :meth:`stall` (the board stops for a while, its clock with it).
- :meth:`mute` (silent: hears and says nothing, not even its own shutdown),
  :meth:`jump_clock` (its clock jumps by so many seconds, nothing else changes),
  :meth:`unplug` / :meth:`replug` (the device goes away and comes back at the same path, as a
  USB adapter's ``/dev/serial/by-id`` link does; the board keeps running meanwhile, and its
  output watchdog with it).

The host is pointed at :attr:`path`, a symbolic link to the current pty in ``folder``. The
noise is written by a process of its own, as fast as the host reads it; what the host has not
read when it ends is discarded.
"""

from __future__ import annotations

import os
import pty
import subprocess
import sys
import termios
import time
import tty
from pathlib import Path
from typing import Any

from tests.support.virtual_mcu import VirtualMcu, msgproto

# the noise comes from another process, as from a board: a thread of the test process would
# share the interpreter's lock with the server under test, and hold it when preempted
NOISE = """
import os, sys
fd = int(sys.argv[1])
print("ready", flush=True)
chunk = bytes.fromhex(sys.stdin.readline().strip())
os.write(fd, chunk or os.urandom(512))
print("flowing", flush=True)
while True:
    os.write(fd, chunk or os.urandom(512))
"""


class HostileMcu(VirtualMcu):
    """See the module docstring."""

    def __init__(self, folder: Path, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.link_path = folder / "ttyMCU"
        self._point_link()
        self.path = str(self.link_path)
        self.noise_mode: str | None = None
        self._noise: subprocess.Popen[str] | None = None

    def _point_link(self) -> None:
        spare = self.link_path.with_suffix(".new")
        os.symlink(os.ttyname(self._slave), spare)
        os.replace(spare, self.link_path)

    def stop(self) -> None:
        self.noise(None)
        if self.master < 0:
            self.replug()
        super().stop()

    # -- faults -------------------------------------------------------------------------------
    def noise(self, mode: str | None) -> None:
        """Start (``"garbage"``, ``"flood"``) or end (None) the noise; see the docstring."""
        if self._noise is not None:
            self._noise.kill()
            self._noise.wait()
            self._noise = None
            with self.lock:
                termios.tcflush(self._slave, termios.TCIFLUSH)  # unread noise never arrives
            self.noise_mode = None
        if mode is not None:
            assert mode in ("garbage", "flood")
            noise = self._noise = subprocess.Popen(
                [sys.executable, "-c", NOISE, str(self.master)], pass_fds=[self.master],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert noise.stdin is not None and noise.stdout is not None
            noise.stdout.readline()  # started (a while, on a busy machine)
            with self.lock:  # from now on the board's answers are lost in the noise, and
                # the flood's sequence number stays at the last one it acknowledged
                self.noise_mode = mode
                chunk = self._flood_chunk() if mode == "flood" else b""
            noise.stdin.write(chunk.hex() + "\n")
            noise.stdin.flush()
            noise.stdout.readline()  # flowing

    def jump_clock(self, seconds: float) -> None:
        """The board's clock jumps ``seconds`` (forward if positive), nothing else changes."""
        with self.lock:
            self._t0 -= seconds

    def stall(self, seconds: float) -> None:
        """The board stops for ``seconds`` (call from a thread): it reads nothing and its clock
        stands still, then runs on that far behind the host's (a simulated board the host
        starved of CPU does this; its clock never goes back)."""
        with self.lock:
            time.sleep(seconds)
            self._t0 += seconds

    def unplug(self) -> None:
        """The device goes away: the host's reads fail; the board runs on, unheard."""
        with self.lock:
            os.close(self.master)
            os.close(self._slave)
            self.master = self._slave = -1
            self.link_path.unlink()

    def replug(self) -> None:
        """The device comes back at the same path (a new pty); the board as it was."""
        with self.lock:
            self.master, self._slave = pty.openpty()
            tty.setraw(self._slave)
            self._buffer.clear()
            self._point_link()

    # -- what the board sends -----------------------------------------------------------------
    def _send_block(self, payload: bytes) -> None:
        if self.noise_mode is None and self.master >= 0 and not self.muted:  # lost, unsaid
            super()._send_block(payload)

    def _flood_chunk(self) -> bytes:
        """Blocks of ``stats`` messages whose acknowledgement never moves (the sequence
        number of the first block the board expected when the flood began)."""
        fmt = self.parser.lookup_command("stats count=%u sum=%u sumsq=%u")
        seq = 0x10 | (self.expected_seq & 0xF)
        out = bytearray()
        for n in range(32):
            block = bytearray([0, seq]) + bytes(fmt.encode([n, 1000 * n, 7 * n]))
            block[0] = len(block) + 3
            block += bytes(msgproto.crc16_ccitt(block)) + bytes([msgproto.MESSAGE_SYNC])
            out += block
        return bytes(out)
