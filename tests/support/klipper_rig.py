"""The klipper-avr rig in a test: stock Klipper firmware in simavr (``run``), its pty, and what
its pins did (the GPIO log, format in the rig's README).

:func:`klipper_rig` starts ``run`` with ``MCU_GPIO_LOG`` in the test's folder, reads the pty
path it prints and stops it (SIGTERM) after the block; :class:`GpioLog` parses the log: pin
edges by cycle, the steps a step/dir pair made, timer 0's compare registers (the hardware PWM
of PB3/PB4) and the host's CLOCK_MONOTONIC at a cycle. The rig runs in real time: tests using
it are few.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

from tests.support.rigs import rig

FREQ_HZ = 20_000_000


@dataclass
class Rig:
    """A running rig: its serial port and its GPIO log file."""

    path: str
    gpio_log: Path
    process: asyncio.subprocess.Process

    def gpio(self) -> GpioLog:
        return GpioLog.read(self.gpio_log)


@contextlib.asynccontextmanager
async def klipper_rig(tmp_path: Path, name: str = "rig") -> AsyncIterator[Rig]:
    """The stock firmware running; skipped (naming the rig) only when the rig is absent."""
    folder = rig("klipper-avr")
    log = tmp_path / f"{name}-gpio.log"
    stderr = (tmp_path / f"{name}-stderr.log").open("wb")
    process = await asyncio.create_subprocess_exec(
        str(folder / "run"), env={**os.environ, "MCU_GPIO_LOG": str(log)},
        stdout=asyncio.subprocess.PIPE, stderr=stderr)
    stderr.close()
    try:
        assert process.stdout is not None
        path = (await asyncio.wait_for(process.stdout.readline(), 10.0)).decode().strip()
        assert path.startswith("/dev/"), f"the rig printed {path!r}"
        yield Rig(path, log, process)
    finally:
        if process.returncode is None:
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), 5.0)
            except TimeoutError:
                process.kill()
                await process.wait()


@dataclass
class GpioLog:
    """One reading of a rig's GPIO log."""

    edges: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # "A0": (cycle, v)
    ocr0: list[tuple[int, int, int, str]] = field(default_factory=list)  # cycle, A, B, TCCR0A
    sync: list[tuple[int, int]] = field(default_factory=list)  # (cycle, host monotonic ns)

    @classmethod
    def read(cls, path: Path) -> GpioLog:
        log = cls()
        for line in path.read_text().splitlines():
            words = line.split()
            if len(words) < 3 or not words[0].isdigit():
                continue
            cycle, kind = int(words[0]), words[1]
            if kind == "T":
                log.sync.append((cycle, int(words[2])))
            elif kind == "OCR0" and len(words) >= 5:
                log.ocr0.append((cycle, int(words[2]), int(words[3]), words[4]))
            elif len(kind) == 2 and kind[0] in "ABCD" and kind[1].isdigit():
                log.edges.setdefault(kind, []).append((cycle, int(words[2])))
        return log

    def level_at(self, pin: str, cycle: int) -> int:
        """The pin's level just before ``cycle`` (0 before any change)."""
        level = 0
        for when, value in self.edges.get(pin, []):
            if when >= cycle:
                break
            level = value
        return level

    def steps(self, step_pin: str, dir_pin: str) -> tuple[int, int, list[int]]:
        """Steps a stepper made: (gross, net with the dir pin's level 1 counted positive,
        the cycle of each step's rising edge)."""
        rises = [cycle for cycle, value in self.edges.get(step_pin, []) if value == 1]
        net = sum(1 if self.level_at(dir_pin, cycle) else -1 for cycle in rises)
        return len(rises), net, rises

    def host_ns(self, cycle: int) -> int:
        """CLOCK_MONOTONIC (ns) at a cycle, from the nearest earlier sync record."""
        before = [(c, ns) for c, ns in self.sync if c <= cycle] or self.sync[:1]
        c, ns = before[-1]
        return ns + (cycle - c) * 1_000_000_000 // FREQ_HZ

    def pwm_pb4(self) -> list[tuple[int, int]]:
        """PB4's duty (OCR0B, of 255) by cycle, on changes."""
        out: list[tuple[int, int]] = []
        for cycle, _, value, _ in self.ocr0:
            if not out or out[-1][1] != value:
                out.append((cycle, value))
        return out


    def pwm_configured(self) -> int:
        """How often timer 0's PWM was set up (``config_pwm_out`` on PB3/PB4 after a boot)."""
        count, last = 0, "00"
        for _, _, _, tccr0a in self.ocr0:
            if tccr0a != "00" and last == "00":
                count += 1
            last = tccr0a
        return count


async def wait_configured(board: Rig, times: int = 1, limit_s: float = 20.0) -> None:
    """Until the firmware has been configured ``times`` times since the rig started."""
    deadline = time.monotonic() + limit_s
    while board.gpio().pwm_configured() < times:
        assert time.monotonic() < deadline, "the board was never configured"
        await asyncio.sleep(0.1)
