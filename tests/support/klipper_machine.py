"""A motiond machine on the Klipper backend, driving a :class:`VirtualMcu` over a real pty."""

from __future__ import annotations

import asyncio
import contextlib
import sys
from collections.abc import AsyncIterator, Iterator
from typing import Any

from server.app import App, TransportFactory
from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.link import Link
from server.runtime import realtime
from server.runtime.clock import RealClock
from tests.conftest import make_config
from tests.support.helpers import running
from tests.support.virtual_mcu import VirtualMcu

LOOP_PRIORITY = 4
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
                          transports: list[TransportFactory] | None = None,
                          **extra: Any) -> AsyncIterator[App]:
    """An in-process server on the real clock whose backend is a KlipperBackend on ``mcu``,
    recording its exact step times; yields once the MCU is configured."""
    config = klipper_config(mcu.path, lead_time_s, max_duration_s, **extra)
    with realtime_loop():
        async with running(config, clock=RealClock(), transports=transports) as app:
            yield await _configured(app)


@contextlib.contextmanager
def realtime_loop() -> Iterator[None]:
    """The test's event loop at real-time priority while the machine runs, as ``motiond
    serve`` runs it (priority 4: below the virtual MCU's thread and the latency probe; a board
    runs on a core of its own, and the instrument must not be what is slow). At ordinary
    priority a loaded machine preempts the loop's thread while it holds the GIL, and the virtual
    MCU's thread, however urgent, waits with it: it then reads steps late and shuts down
    ("Stepper too far in past") where no MCU would. Ordinary priority where not allowed."""
    interval_s = sys.getswitchinterval()
    priority = realtime.claim(LOOP_PRIORITY)
    try:
        yield
    finally:
        if priority.realtime:
            realtime.release(interval_s)


async def _configured(app: App) -> App:
    backend = app.kernel.machine.backend
    assert isinstance(backend, KlipperBackend)
    for axis in backend.axes:
        axis.steps.record = True
    backend.pwm_log = []
    for _ in range(300):
        if backend.ready:
            break
        await asyncio.sleep(0.01)
    assert backend.ready, backend.fault
    return app


@contextlib.asynccontextmanager
async def configured_link(mcu: VirtualMcu) -> AsyncIterator[tuple[Link, Dictionary]]:
    """A link to ``mcu`` whose owner samples, the board configured (one digital output, oid 0
    on PA8) and every block acknowledged; closed when the block ends."""
    link = Link(mcu.path, 250000, lambda name, params, _: None, lambda reason: None)
    link.open()
    try:
        link.dictionary = encode = Dictionary.from_compressed(mcu.blob)
        link.send(encode.encode("allocate_oids", count=1),
                  encode.encode("config_digital_out", oid=0, pin="PA8", value=0,
                                default_value=0, max_duration=0),
                  encode.encode("finalize_config", crc=1))
        for _ in range(200):
            if mcu.configured and not link.in_flight:
                break
            await asyncio.sleep(0.01)
        link.sample()
        yield link, encode
    finally:
        link.close()
