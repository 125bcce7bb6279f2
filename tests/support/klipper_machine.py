"""A motiond machine on the Klipper backend, driving a :class:`VirtualMcu` over a real pty."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

from server.app import App
from server.backends.klipper.backend import KlipperBackend
from server.runtime.clock import RealClock
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.virtual_mcu import VirtualMcu

PINS = {"x": {"step_pin": "PB13", "dir_pin": "!PB12", "enable_pin": "!PB14"},
        "y": {"step_pin": "PB10", "dir_pin": "PB2", "enable_pin": "!PB11"},
        "z": {"step_pin": "PB0", "dir_pin": "PC5", "enable_pin": "!PB1"}}


def klipper_config(path: str, lead_time_s: float = 0.2, max_duration_s: float = 1.0,
                   **extra: Any) -> Any:
    backend = {"kind": "klipper", "serial": path, "lead_time_s": lead_time_s, "axes": PINS,
               "outputs": {"PA8": {"pwm": True, "cycle_time_s": 0.0002,
                                   "max_duration_s": max_duration_s}}}
    return make_config(backend=backend, **extra)


@contextlib.asynccontextmanager
async def klipper_machine(mcu: VirtualMcu, lead_time_s: float = 0.2, max_duration_s: float = 1.0,
                          **extra: Any) -> AsyncIterator[App]:
    """An in-process server on the real clock whose backend is a KlipperBackend on ``mcu``,
    recording its exact step times; yields once the MCU is configured."""
    config = klipper_config(mcu.path, lead_time_s, max_duration_s, **extra)
    async with running(config, clock=RealClock()) as app:
        machine = app.kernel.machine
        backend = machine.backend
        assert isinstance(backend, KlipperBackend)
        for axis in backend.axes:
            axis.exact = []
        backend.pwm_log = []
        for _ in range(300):
            if backend.ready:
                break
            await asyncio.sleep(0.01)
        assert backend.ready, backend.fault
        yield app
