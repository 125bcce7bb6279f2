"""The lines a job runs between its own (pure asyncio, no machine): in order, at most once."""

from __future__ import annotations

import asyncio

import pytest

from server.errors import CommandError, Error
from server.jobs.interjections import PENDING_LINES, Interjections


async def test_lines_run_in_order_once_and_the_job_end_leaves_the_rest_unrun() -> None:
    interjections, ran = Interjections(), []

    async def submit(text: str, ticket: int) -> list[str]:
        if ticket != 7:
            raise CommandError(Error.BUSY, "a stop came after this line was sent: not run")
        ran.append(text)
        return [f"did {text}"]

    first, stale = interjections.add("M290 Z0.05", 7), interjections.add("M290 Z1", 6)
    await interjections.run(submit)
    assert await first == ["did M290 Z0.05"] and ran == ["M290 Z0.05"]
    with pytest.raises(CommandError):
        await stale
    late = interjections.add("M290 Z0.1", 7)
    interjections.release()
    await interjections.run(submit)
    assert await late is None and ran == ["M290 Z0.05"], "released: it never runs"


async def test_a_line_cut_short_by_the_job_stopping_is_refused_never_offered_again() -> None:
    interjections = Interjections()
    entered = asyncio.Event()

    async def slow(text: str, ticket: int) -> list[str]:
        entered.set()
        await asyncio.sleep(10)
        return []

    answer = interjections.add("M290 Z0.05", 1)
    player = asyncio.create_task(interjections.run(slow))
    await entered.wait()
    player.cancel()
    with pytest.raises(asyncio.CancelledError):
        await player
    with pytest.raises(CommandError, match="stopped while the line ran"):
        await answer
    assert not interjections.waiting


async def test_the_waiting_lines_are_bounded() -> None:
    interjections = Interjections()
    for _ in range(PENDING_LINES):
        interjections.add("M290 Z0.01", 1)
    with pytest.raises(CommandError) as refused:
        interjections.add("M290 Z0.01", 1)
    assert refused.value.code == 45
