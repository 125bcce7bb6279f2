"""The dispatcher routes every kind of line, keeps one order, and refuses the unknown."""

from __future__ import annotations

import asyncio

import pytest

from server.errors import CommandError
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.runtime.dispatcher import Command, Dispatcher, SystemSource
from server.runtime.turn import Turn

SMALL = InterpreterSettings(("X", "Y", "Z"), (0.0, 0.0, -50.0), (400.0, 300.0, 50.0))

SOURCE = SystemSource()


async def test_every_g_code_line_goes_whole_to_the_interpreter_handler() -> None:
    seen: list[str] = []
    dispatcher = Dispatcher()
    classify = Interpreter(SMALL).classify
    dispatcher.set_gcode_handler(lambda c: seen.append(c.text) or ["msg"], classify)
    assert await dispatcher.submit("m106 s128", SOURCE) == ["msg"]
    assert await dispatcher.submit("G1 X10 F600 M106", SOURCE) == ["msg"]
    assert seen == ["m106 s128", "G1 X10 F600 M106"]


@pytest.mark.parametrize("name", ["M106", "G28.2", "m3"])
def test_g_and_m_codes_cannot_be_registered_as_commands(name: str) -> None:
    with pytest.raises(ValueError, match="interpreter"):
        Dispatcher().register(name, lambda c: None)


async def test_m117_and_m118_take_the_rest_of_the_line_as_text() -> None:
    got: list[str] = []
    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(lambda c: ["gcode"], Interpreter(SMALL).classify)
    dispatcher.register("M117", lambda c: got.append(c.args) or None)
    assert await dispatcher.submit("M117 Done! (100%)", SOURCE) == []
    assert await dispatcher.submit("m0117", SOURCE) == []
    assert await dispatcher.submit("M1170", SOURCE) == ["gcode"]
    assert got == ["Done! (100%)", ""]


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


async def test_several_handlers_for_one_command_all_run_in_order() -> None:
    order: list[int] = []
    dispatcher = Dispatcher()
    dispatcher.register("hello", lambda c: order.append(1) or ["a"])
    dispatcher.register("hello", lambda c: order.append(2) or ["b"])
    assert await dispatcher.submit("hello", SOURCE) == ["a", "b"]
    assert order == [1, 2]


@pytest.mark.parametrize("line, code", [("$Q", 2), ("$", 2), ("G1 X", 2), ("#1=5", 1)])
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
    dispatcher.set_gcode_handler(lambda c: None, Interpreter(SMALL).classify)
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
    dispatcher.set_gcode_handler(slow, Interpreter(SMALL).classify)
    first = asyncio.create_task(dispatcher.submit("G1 X1", SystemSource("a")))
    second = asyncio.create_task(dispatcher.submit("G1 X2", SystemSource("b")))
    await asyncio.sleep(0.01)
    assert order == ["start G1 X1"]
    gate.set()
    await asyncio.gather(first, second)
    assert order == ["start G1 X1", "end G1 X1", "start G1 X2", "end G1 X2"]


async def test_a_line_that_needs_no_wait_is_done_within_begin_and_leaves_the_turn_free() -> None:
    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(lambda c: ["done"], Interpreter(SMALL).classify)
    assert dispatcher.begin("G1 X1", SOURCE) == ["done"]  # no awaitable: nothing to wait for
    with pytest.raises(CommandError):
        dispatcher.begin("G5 X1 $", SOURCE)  # refused at once, the turn given back
    assert dispatcher.begin("G1 X2", SOURCE) == ["done"]


async def test_a_line_arriving_while_another_waits_for_its_turn_never_overtakes_it() -> None:
    order: list[str] = []
    gate = asyncio.Event()

    async def handler(command: Command) -> list[str]:
        if command.text == "G1 X1":
            await gate.wait()
        order.append(command.text)
        return []

    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(handler, Interpreter(SMALL).classify)
    first = asyncio.create_task(dispatcher.submit("G1 X1", SystemSource("a")))
    second = asyncio.create_task(dispatcher.submit("G1 X2", SystemSource("a")))
    await asyncio.sleep(0.01)
    gate.set()  # the turn goes to the second line, which has not run yet when the third comes
    await asyncio.sleep(0)
    third = asyncio.create_task(dispatcher.submit("G1 X3", SystemSource("a")))
    await asyncio.gather(first, second, third)
    assert order == ["G1 X1", "G1 X2", "G1 X3"]


async def test_a_line_cancelled_while_it_waits_for_its_turn_never_runs_nor_blocks_others() -> None:
    gate = asyncio.Event()
    ran: list[str] = []

    async def handler(command: Command) -> list[str]:
        if command.text == "G1 X1":
            await gate.wait()
        ran.append(command.text)
        return []

    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(handler, Interpreter(SMALL).classify)
    first = asyncio.create_task(dispatcher.submit("G1 X1", SystemSource("a")))
    waiting = asyncio.create_task(dispatcher.submit("G1 X2", SystemSource("a")))
    last = asyncio.create_task(dispatcher.submit("G1 X3", SystemSource("a")))
    await asyncio.sleep(0.01)
    waiting.cancel()
    gate.set()
    await asyncio.gather(first, waiting, return_exceptions=True)
    await asyncio.wait_for(last, 1.0)
    assert ran == ["G1 X1", "G1 X3"]
    assert await asyncio.wait_for(dispatcher.submit("G1 X4", SOURCE), 1.0) == []


async def test_a_released_turn_goes_to_the_first_waiter_and_nobody_overtakes_it() -> None:
    turn = Turn()
    await turn.take()
    first = asyncio.create_task(turn.take())
    await asyncio.sleep(0)
    turn.release()
    assert not turn.free  # handed over before the waiter runs: a newcomer must wait
    newcomer = asyncio.create_task(turn.take())
    await first
    await asyncio.sleep(0)
    assert not newcomer.done()
    turn.release()
    await asyncio.wait_for(newcomer, 1.0)
    turn.release()
    assert turn.free


async def test_a_turn_handed_to_a_waiter_cancelled_before_it_ran_goes_to_the_next() -> None:
    turn = Turn()
    await turn.take()
    handed = asyncio.create_task(turn.take())
    after = asyncio.create_task(turn.take())
    await asyncio.sleep(0)
    turn.release()  # handed over: nobody may take it meanwhile
    assert not turn.free
    handed.cancel()  # before it ran
    await asyncio.gather(handed, return_exceptions=True)
    await asyncio.wait_for(after, 1.0)
    turn.release()
    assert turn.free


async def test_read_only_sources_may_query_but_not_move() -> None:
    dispatcher = Dispatcher()
    dispatcher.set_gcode_handler(lambda c: ["ran"], Interpreter(SMALL).classify)
    dispatcher.register("$G", lambda c: ["[GC:G0]"], query=True)
    dispatcher.register("$C", lambda c: ["[MSG:Enabled]"])
    observer = SystemSource("observer", can_control=False)
    assert await dispatcher.submit("$G", observer) == ["[GC:G0]"]
    assert await dispatcher.submit("M114", observer) == ["ran"]
    for line in ("G1 X1", "$C", "F100", "M114 G1 X150 Y100 F3000 M3 S1000", "M114 M3"):
        with pytest.raises(CommandError) as info:
            await dispatcher.submit(line, observer)
        assert info.value.code == 46, line


async def test_while_one_source_runs_motion_others_may_query_but_not_change_state() -> None:
    busy = True
    dispatcher = Dispatcher(is_busy=lambda: busy)
    dispatcher.set_gcode_handler(lambda c: ["ran"], Interpreter(SMALL).classify)
    dispatcher.register("$G", lambda c: ["[GC:G0]"], query=True)
    dispatcher.register_immediate("abort", lambda c: ["aborted"])
    streamer, other = SystemSource("streamer"), SystemSource("other")
    assert await dispatcher.submit("G1 X10 F600", streamer) == ["ran"]
    for line in ("G92 X0", "G91", "G20", "G0 X1"):
        with pytest.raises(CommandError) as info:
            await dispatcher.submit(line, other)
        assert info.value.code == 45, line
    assert await dispatcher.submit("$G", other) == ["[GC:G0]"]
    assert await dispatcher.submit("abort", other) == ["aborted"]
    assert await dispatcher.submit("G1 X20", streamer) == ["ran"]
    busy = False
    assert await dispatcher.submit("G0 X0", other) == ["ran"], "idle: anyone may take over"


@pytest.mark.parametrize("text, kind", [
    ("M114", "query"), ("N7 M114", "query"), ("M112", "unlock"), ("M999", "unlock"),
    ("G28.2 X0", "unlock"), ("G1 X1", "effect"), ("M114 G1 X1", "effect"),
    ("M114 F100", "effect"), ("M1.5", "effect"), ("M3 S100", "effect"), ("G28.2 F100", "effect"),
])
def test_a_line_is_classified_from_every_word(text: str, kind: str) -> None:
    from server.gcode.parser import parse_line

    assert Interpreter(SMALL).classify(parse_line(text)).value == kind
