"""The dispatcher routes every kind of line, keeps one order, and refuses the unknown."""

from __future__ import annotations

import asyncio

import pytest

from server.dispatcher import Command, Dispatcher, SystemSource
from server.errors import CommandError

SOURCE = SystemSource()


async def test_g_and_m_codes_with_handlers_reach_them_and_the_rest_goes_to_gcode() -> None:
    seen: list[str] = []
    dispatcher = Dispatcher()
    dispatcher.register("M106", lambda c: seen.append(f"fan {c.line.get('S')}") or None)
    dispatcher.set_gcode_handler(lambda c: seen.append(f"gcode {c.text}") or ["msg"])
    assert await dispatcher.submit("m106 s128", SOURCE) == []
    assert await dispatcher.submit("G1 X1", SOURCE) == ["msg"]
    assert seen == ["fan 128.0", "gcode G1 X1"]


async def test_named_and_dollar_commands_get_their_arguments() -> None:
    got: list[tuple[str, str]] = []
    dispatcher = Dispatcher()
    dispatcher.register("fire", lambda c: got.append((c.name, c.args)) or None)
    dispatcher.register("$J=", lambda c: got.append((c.name, c.args)) or None)
    dispatcher.register("$=", lambda c: got.append((c.name, c.args)) or None)
    dispatcher.register("$H", lambda c: got.append((c.name, c.args)) or None)
    for line in ("FIRE 50", "$J=G91 X1 F100", "$110 = 500", "$h"):
        await dispatcher.submit(line, SOURCE)
    assert got == [("fire", "50"), ("$J=", "G91 X1 F100"), ("$=", "110 = 500"), ("$H", "")]


async def test_several_handlers_for_one_code_all_run_in_order() -> None:
    order: list[int] = []
    dispatcher = Dispatcher()
    dispatcher.register("M7", lambda c: order.append(1) or ["a"])
    dispatcher.register("M7", lambda c: order.append(2) or ["b"])
    assert await dispatcher.submit("M7", SOURCE) == ["a", "b"]
    assert order == [1, 2]


@pytest.mark.parametrize("line, code", [("$Q", 3), ("$", 3), ("G1 X", 2), ("#1=5", 1)])
async def test_unknown_commands_are_errors_never_silent(line: str, code: int) -> None:
    dispatcher = Dispatcher()
    with pytest.raises(CommandError) as info:
        await dispatcher.submit(line, SOURCE)
    assert info.value.code == code


async def test_empty_and_comment_lines_need_no_handler() -> None:
    dispatcher = Dispatcher()
    assert await dispatcher.submit("", SOURCE) == []
    assert await dispatcher.submit("(just a comment)", SOURCE) == []


async def test_gcode_is_locked_out_in_alarm_but_unlock_is_not() -> None:
    locked = True
    dispatcher = Dispatcher(is_locked=lambda: locked)
    dispatcher.set_gcode_handler(lambda c: None)
    dispatcher.register("$X", lambda c: None, when_locked=True)
    with pytest.raises(CommandError) as info:
        await dispatcher.submit("G0 X1", SOURCE)
    assert info.value.code == 9
    assert await dispatcher.submit("$X", SOURCE) == []


async def test_one_ordered_stream_across_sources() -> None:
    order: list[str] = []
    gate = asyncio.Event()

    async def slow(command: Command) -> None:
        order.append(f"start {command.text}")
        await gate.wait()
        order.append(f"end {command.text}")

    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(slow)
    first = asyncio.create_task(dispatcher.submit("G1 X1", SystemSource("a")))
    second = asyncio.create_task(dispatcher.submit("G1 X2", SystemSource("b")))
    await asyncio.sleep(0.01)
    assert order == ["start G1 X1"]
    gate.set()
    await asyncio.gather(first, second)
    assert order == ["start G1 X1", "end G1 X1", "start G1 X2", "end G1 X2"]


async def test_read_only_sources_may_query_but_not_move() -> None:
    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(lambda c: ["moved"])
    dispatcher.register("$G", lambda c: ["[GC:G0]"])
    observer = SystemSource("observer", can_control=False)
    assert await dispatcher.submit("$G", observer) == ["[GC:G0]"]
    with pytest.raises(CommandError):
        await dispatcher.submit("G1 X1", observer)
