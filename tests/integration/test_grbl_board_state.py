"""The grbl backend is busy only while the board is: its reports and the motion in its buffer,
never "a line was forwarded" (a scripted controller over TCP, as in test_grbl_fake_controller).
"""

from __future__ import annotations

from pathlib import Path

from server.backends.grbl.machine import GrblMachine
from server.runtime.events import MachineState
from tests.integration.test_grbl_fake_controller import client_of, linked
from tests.support.senders import CharCountingClient, wait_for


async def front_report(client: CharCountingClient) -> str:
    """The front's answer to ``?``."""
    client.writer.write(b"?")
    while not (line := await client._line(2.0)).startswith("<"):
        pass
    return line


async def test_another_clients_job_runs_right_after_a_dollar_x(tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        first, second = await client_of(app), await client_of(app)
        try:
            assert (await first.command("$X"))[-1] == "ok"
            assert app.kernel.state is MachineState.IDLE, "$X moves nothing"
            result = await second.stream([f"G1 X{n % 7} F600" for n in range(40)])
            assert result.replies == ["ok"] * 40, "nobody owns an idle machine"
        finally:
            await first.close()
            await second.close()


async def test_a_jog_right_after_any_command_is_the_boards_to_run(tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            for command in ("$X", "G21", "M5", "G10 L20 P1 X0"):
                assert (await client.command(command))[-1] == "ok"
                assert (await client.command("$J=G91 X1 F100"))[-1] == "ok", command
                await wait_for(lambda: not app.kernel.machine.busy, 2.0, "the jog done")
        finally:
            await client.close()
        assert fake.lines[-2:] == ["G10L20P1X0", "$J=G91X1F100"]


async def test_motion_sent_is_run_at_the_front_until_a_report_after_its_answer_says_idle(
        tmp_path: Path) -> None:
    """Grbl reports Idle for a moment after the ok of a move it has not yet started; the
    front says Run (and the sender owns the machine) until a poll sent after every answer
    comes back Idle."""
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client, other = await client_of(app), await client_of(app)
        try:
            fake.polls_answered = False  # the board's reports lag
            assert (await client.command("G0 X5"))[-1] == "ok"
            assert machine.busy and app.kernel.state is MachineState.RUN
            assert (await front_report(other)).startswith("<Run|"), "the board said Idle before"
            assert (await other.command("G0 X1"))[-1] == "error:45", "the owner's motion runs"
            assert (await other.command("$G"))[-1] == "ok", "a query is anyone's"
            fake.polls_answered = True
            await wait_for(lambda: not machine.busy, 2.0, "a report after the answer")
            assert app.kernel.state is MachineState.IDLE
            assert (await front_report(other)).startswith("<Idle|")
            assert (await other.command("G0 X1"))[-1] == "ok"
        finally:
            await client.close()
            await other.close()


async def test_motionds_own_codes_on_a_line_with_a_move_are_refused_whole_but_a_stop_stops(
        tmp_path: Path) -> None:
    """M114, M400... are motiond's (Grbl has none: error 20, 23 from M256 on, as the rig
    answers): mixed with words for the board, the line is refused and nothing of it runs, in
    motiond or on the board; alone they run here. M112 on any line stops."""
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await client_of(app)
        try:
            for line, error in (("G1 X10 F100 M114", 20), ("G20 M400", 23), ("M115 G0 X5", 20)):
                assert (await client.command(line))[-1] == f"error:{error}", line
            assert machine.interpreter.gc_report().startswith("[GC:G0 G54 G17 G21 G90")
            assert machine.interpreter.position == (0.0, 0.0)
            assert not any(text.startswith(("G1X10", "G20", "M115")) for text in fake.lines)
            assert (await client.command("M114"))[-1] == "ok"
            assert (await client.command("M400"))[-1] == "ok"
            client.writer.write(b"G1 X10 F100 M112\n")
            await wait_for(lambda: app.kernel.state is MachineState.ALARM, 2.0, "the halt")
            assert not any(text.startswith("G1X10") for text in fake.lines)
        finally:
            await client.close()
