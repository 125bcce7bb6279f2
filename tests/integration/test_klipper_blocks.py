"""Messages share message blocks: a burst leaves in as few blocks as fit, in order, and
motion with the laser packs several messages to a block with every step still exact."""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any

from server.backends.klipper.backend import KlipperBackend
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.link import Link
from tests.integration.test_klipper_backend import LASER, check_steps, run_job
from tests.support.klipper_machine import klipper_machine
from tests.support.virtual_mcu import VirtualMcu


async def test_a_burst_of_small_messages_leaves_in_full_blocks_decoded_in_order(
    mcu: VirtualMcu
) -> None:
    responses: list[int] = []
    link = Link(mcu.path, 250000, lambda name, params, _: responses.append(params["offset"])
                if name == "identify_response" else None, lambda reason: None)
    link.open()
    try:
        messages = [link.dictionary.encode("identify", offset=k, count=1) for k in range(100)]
        link.send(*messages)
        for _ in range(200):
            if len(responses) == len(messages):
                break
            await asyncio.sleep(0.01)
        total = sum(len(m) for m in messages)
        assert {len(m) for m in messages} == {3, 4}  # offsets past 95 take two bytes
        assert mcu.blocks_received == packed_blocks(messages)
        assert mcu.blocks_received <= math.ceil(total / (PAYLOAD_MAX - 3))  # 6 for 100
        received = [p["offset"] for _, name, p in mcu.commands if name == "identify"]
        assert received == list(range(100)), "every message decoded once, in order"
        assert responses == list(range(100))
        assert link.retransmits == 0
    finally:
        link.close()


def packed_blocks(messages: list[bytes]) -> int:
    """Blocks of at most PAYLOAD_MAX bytes, filled in order."""
    blocks, size = 0, PAYLOAD_MAX
    for message in messages:
        if size + len(message) > PAYLOAD_MAX:
            blocks, size = blocks + 1, 0
        size += len(message)
    return blocks


async def test_a_laser_job_sends_several_messages_a_block_and_every_step_lands(
    mcu: VirtualMcu
) -> None:
    async with klipper_machine(mcu, laser=LASER) as app:
        backend = app.kernel.machine.backend
        assert isinstance(backend, KlipperBackend) and backend.mcu is not None
        await asyncio.sleep(0.2)
        before_blocks, before_messages = mcu.blocks_received, len(mcu.commands)
        zigzag = [f"G1 X{20 + 0.5 * k:g} Y{5 + (k % 2) * 0.5:g} S{200 + 40 * (k % 20)}"
                  for k in range(40)]
        await run_job(app, ["M4 S1000", "G1 X20 Y5 F3000", *zigzag, "M5"])
        blocks = mcu.blocks_received - before_blocks
        messages = len(mcu.commands) - before_messages
        check_steps(app, mcu)
        # one message a block before (each sent as it was made); the polls' get_clock and
        # get_config stay one a block, as the firmware wants them (never back to back)
        assert messages >= 2.0 * blocks, (messages, blocks)


async def test_a_riding_request_joins_the_next_block_or_leaves_alone_when_none_comes(
    mcu: VirtualMcu
) -> None:
    link = Link(mcu.path, 250000, lambda name, params, _: None, lambda reason: None)
    link.open()
    try:
        def ask(offset: int, ride_s: float) -> Any:
            return link.request(link.dictionary.encode("identify", offset=offset, count=1),
                                "identify_response", 2.0, lambda p: p["offset"] == offset,
                                ride_s=ride_s)

        started = time.monotonic()
        reply = await ask(0, 0.1)
        assert reply["#sent_s"] >= started + 0.1, "it waited for company, then left alone"
        assert mcu.block_messages == [["identify"]]
        riding = asyncio.ensure_future(ask(1, 1.0))
        await asyncio.sleep(0.05)
        assert len(mcu.block_messages) == 1, "not sent before company came"
        company = time.monotonic()
        link.send(link.dictionary.encode("identify", offset=2, count=1))
        reply = await riding
        assert company <= reply["#sent_s"] < company + 0.05  # when its block left
        assert mcu.block_messages[-1] == ["identify", "identify"]
        assert [p["offset"] for _, name, p in mcu.commands if name == "identify"] == [0, 1, 2]
        assert link.retransmits == 0
    finally:
        link.close()
