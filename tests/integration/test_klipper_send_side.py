"""The link's send side costs per burst, not per block (issue #26, part M): the blocks a burst
fills leave in one write, and blocks sent behind one still in flight keep its retransmission
timer (its deadline is the oldest block's). The virtual MCU over a real pty receives and
acknowledges every block."""

from __future__ import annotations

import asyncio

from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.link import Link
from tests.support.klipper_machine import klipper_machine
from tests.support.virtual_mcu import VirtualMcu


async def idle_link(backend: object) -> Link:
    assert isinstance(backend, KlipperBackend) and backend.mcu is not None
    link = backend.mcu.link
    for _ in range(200):  # the configuration's blocks acknowledged
        if not link.window.inflight and not link.queued_bytes:
            break
        await asyncio.sleep(0.01)
    assert not link.window.inflight
    return link


async def test_a_burst_of_three_blocks_leaves_in_one_write(mcu: VirtualMcu) -> None:
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        link = await idle_link(backend)
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        message = backend.mcu.dictionary.encode("set_next_step_dir", oid=2, dir=0)
        burst = [message] * (2 * (PAYLOAD_MAX // len(message)) + 1)  # two blocks and a bit
        writes: list[int] = []
        flush = link._flush_out

        def counted() -> None:
            writes.append(len(link._out))
            flush()

        link._flush_out = counted  # type: ignore[method-assign]
        blocks, sent = link.window.next_seq, link.bytes_sent
        link.send(*burst)
        assert link.window.next_seq - blocks == 3
        assert writes == [link.bytes_sent - sent]  # one write, of all three blocks
        for _ in range(200):
            if not link.window.inflight:
                break
            await asyncio.sleep(0.01)
        assert not link.window.inflight, "the MCU acknowledged all three"
        assert link.window.retransmits == 0


async def test_blocks_sent_behind_one_in_flight_keep_its_retransmission_timer(
        mcu: VirtualMcu) -> None:
    async with klipper_machine(mcu) as app:
        backend = app.kernel.machine.backend
        link = await idle_link(backend)
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        message = backend.mcu.dictionary.encode("set_next_step_dir", oid=2, dir=0)
        link.send(message)
        timer = link._timer
        assert timer is not None and link.window.inflight
        link.send(message)  # no acknowledgement read in between: the deadline stands
        link.send(message)
        assert link._timer is timer and not timer.cancelled()
        assert len(link.window.inflight) == 3
        for _ in range(200):
            if not link.window.inflight:
                break
            await asyncio.sleep(0.01)
        assert not link.window.inflight and link.window.retransmits == 0
        assert link._timer is None or link._timer is not timer  # re-armed or gone once acked
