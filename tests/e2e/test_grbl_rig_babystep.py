"""M290 (babystep, SET_GCODE_OFFSET's line) through motiond to real Grbl 1.1h (grbl-sim), which
does not know it: the board gets lines it runs, also while it runs a move, and afterwards its own
``$#`` G92, its ``?`` positions and its ``$G`` are what motiond's interpreter says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from server.backends.grbl.machine import GrblMachine
from server.runtime.events import MachineState
from tests.e2e.test_grbl_rig import connect, fronted, modes, same_modes
from tests.e2e.test_grblhal_rig import fronted as hal_fronted
from tests.support.grbl_rig import FAST_SETTINGS, GrblClient, grbl_direct
from tests.support.senders import wait_for

pytestmark = pytest.mark.usefixtures("quick_thread_switches")
_NUMBERS = re.compile(r"-?\d+\.\d+")


async def board_state(client: GrblClient, machine: GrblMachine) -> list[float]:
    """The board's G92 offset (its ``$#``), MPos and WCO (a ``?`` with WCO in it, after two
    more of the board's own reports: Grbl sends WCO in the first after an offset changed, and
    until its reports agree with its ``$#``), one list, once it is still (Grbl answers ``$#``
    only then)."""
    polls = machine.controller.status_polls
    await wait_for(lambda: machine.controller.status_polls >= polls + 2, 5.0, "two polls")
    state: list[float] = []  # (no report with WCO at all: the comparison fails)
    await client.settle()
    for _ in range(40):  # (a loaded machine: the report with the new WCO may come later)
        report = await client.report()
        if "|WCO:" not in report:
            continue
        g92 = next(text for text in await client.send("$#") if text.startswith("[G92:"))
        fields = dict(field.split(":", 1) for field in report.strip("<>").split("|")[1:])
        state = [float(v) for text in (g92, fields["MPos"], fields["WCO"])
                 for v in _NUMBERS.findall(text)]
        if state[6:] == state[:3]:  # G54 is zero here: the board's WCO is its G92
            break
    return state


def ours(machine: GrblMachine) -> list[float]:
    """The same as motiond's interpreter has them."""
    g92 = next(text for text in machine.interpreter.offsets_report() if text.startswith("[G92"))
    return [*(float(v) for v in _NUMBERS.findall(g92)), *machine.interpreter.position,
            *machine.interpreter.wco()]


async def test_the_boards_own_answers_the_translation_rests_on(tmp_path: Path) -> None:
    """Grbl 1.1h directly: M290 is unknown; G92's axis words are refused under G80; a bare
    G1 is accepted only with a feed rate (not after F0, nor under G93), a bare G2 never; G53
    takes machine values under G91."""
    lines = ["M290 Z1", "G80", "G92 Z1", "G0", "G92 Z1", "G92.1", "G80", "G1", "G1 X1 F6000",
             "G1", "G2", "G93", "G1", "G94", "G91", "G53 G0 Z5", "G90"]
    async with grbl_direct(tmp_path) as board:
        for setting in FAST_SETTINGS:
            await board.send(setting)
        replies = [(await board.send(text))[-1] for text in lines]
        report = await board.settle()
    assert replies == ["error:23", "ok", "error:31", "ok", "ok", "ok", "ok", "error:22", "ok",
                       "ok", "error:26", "ok", "error:22", "ok", "ok", "ok", "ok"]
    assert report.startswith("<Idle|MPos:1.000,0.000,5.000|"), report


async def test_m290_becomes_lines_grbl_runs_leaving_its_offsets_position_and_modes_motionds(
        tmp_path: Path) -> None:
    async with fronted(tmp_path) as app:
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await connect(app)
        try:
            assert (await client.send("G1 X5 Z-10 F6000"))[-1] == "ok"
            await client.settle()
            before = await modes(client)
            assert (await client.send("G1 X60"))[-1] == "ok"  # the board runs it...
            assert (await client.send("M290 Z0.5"))[-1] == "ok"  # ...as this arrives
            board = await board_state(client, machine)
            assert board == pytest.approx(ours(machine), abs=1e-3)
            assert board == pytest.approx([0, 0, 0.5, 60, 0, -9.5, 0, 0, 0.5], abs=1e-3)
            assert (await client.send("G1 Z-5"))[-1] == "ok"
            z_mm = (await board_state(client, machine))[5]
            assert z_mm == pytest.approx(-4.5, abs=1e-3), "the next move shifted"
            after = await modes(client)
            assert after == before and after.startswith("[GC:G1 "), "the motion mode kept"
            assert same_modes(after, machine.interpreter.gc_report())

            assert (await client.send("G20"))[-1] == "ok"
            before = await modes(client)
            assert (await client.send("M290 Z0.02 P0"))[-1] == "ok"  # 0.508 mm, no move
            board = await board_state(client, machine)
            assert board == pytest.approx(ours(machine), abs=1e-3)
            assert board == pytest.approx([0, 0, 1.008, 60, 0, -4.5, 0, 0, 1.008], abs=1e-3)
            assert await modes(client) == before
            assert (await client.send("G21"))[-1] == "ok"  # (Grbl's $G shows F in mm/min
            assert same_modes(await modes(client), machine.interpreter.gc_report())  # in G20)
        finally:
            client.close()


async def test_a_baby_step_between_a_running_jobs_lines_shifts_the_boards_later_moves(
        tmp_path: Path) -> None:
    """SET_GCODE_OFFSET's way in a job (``Jobs.interject``): the board runs, so no ``$J=``;
    the job's later moves land 0.5 mm higher on the board, its modes untouched."""
    job = "G21 G90 G1 F6000\n" + "".join(f"G1 X{2 * i} Z{1 + i % 2}\n" for i in range(1, 41))
    async with fronted(tmp_path) as app:
        machine, jobs = app.kernel.machine, app.kernel.jobs
        assert isinstance(machine, GrblMachine)
        await jobs.save("zigzag.nc", job.encode())
        jobs.play("zigzag.nc")
        await wait_for(lambda: machine.interpreter.position[0] >= 10, 10.0, "the job under way")
        assert app.kernel.state is MachineState.RUN
        answer = jobs.interject("M290 Z0.5", app.kernel.status.ticket())
        assert answer is not None
        assert await answer == [], "run between the job's lines, the board's ok"
        assert machine.interpreter.position[0] < 80, "in the middle of the job"
        await wait_for(lambda: not jobs.running and not machine.busy, 20.0, "the job done")
        assert jobs.progress().state == "done"  # type: ignore[union-attr]
        client = await connect(app)
        try:
            board = await board_state(client, machine)
            assert board == pytest.approx([0, 0, 0.5, 80, 0, 1.5, 0, 0, 0.5], abs=1e-3)
            assert same_modes(await modes(client), machine.interpreter.gc_report())
            assert (await modes(client)).startswith("[GC:G1 G54 G17 G21 G90 G94")
        finally:
            client.close()


async def test_grblhal_runs_the_same_lines(tmp_path: Path) -> None:
    """grblHAL does not know M290 either (error:20): the same lines, the same result (its
    ``$G`` differs from Grbl's: it shows G92 while an offset is in force, and more groups)."""
    async with hal_fronted(tmp_path) as app:
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await connect(app)
        try:
            for line in ("G1 X5 Z-10 F6000", "M290 Z0.5", "G1 Z-5", "M290 Z0.25 P0"):
                assert (await client.send(line))[-1] == "ok", line
            board = await board_state(client, machine)
            assert board == pytest.approx(ours(machine), abs=1e-3)
            assert board == pytest.approx([0, 0, 0.75, 5, 0, -4.5, 0, 0, 0.75], abs=1e-3)
            gc = [text for text in await client.send("$G") if "GC:" in text]
            assert gc and gc[0].partition("[GC:")[2].startswith("G1 "), gc
        finally:
            client.close()
