"""Baby-steps during a job: a line run between the job's lines (``Jobs.interject``), as
Klipper's ``SET_GCODE_OFFSET Z_ADJUST=.. MOVE=1`` runs in the move queue: the job's later
moves shifted exactly, applied once, voided by a stop, held with a paused job."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from server.app import App
from server.errors import CommandError
from tests.conftest import make_config
from tests.integration.test_klippy_api_socket import client, served
from tests.support.helpers import SOURCE, running

Target = tuple[float, float, float]
LINES = 40
TARGETS: list[Target] = [(float(i), 0.0, -1.0 - i % 2) for i in range(1, LINES + 1)]
JOB = "G21 G90 G1 F3000\n" + "".join(f"G1 X{x:g} Z{z:g}\n" for x, _, z in TARGETS)
DZ_MM = 0.05  # 20 steps of Z at 400 steps/mm


def recording(app: App) -> list[Target]:
    """Every move target the planner takes from now on (the real planner still plans it)."""
    planner, taken = app.kernel.machine.planner, []
    append = planner.append

    def append_and_record(move):  # type: ignore[no-untyped-def]
        taken.append(move.target_mm)
        return append(move)

    planner.append = append_and_record  # type: ignore[method-assign]
    return taken


def shifted_once_after(taken: list[Target], dz_mm: float) -> int:
    """The number of job moves planned before the baby-step, checking that the step moved Z
    by ``dz_mm`` alone and that every job move after it is the file's, shifted exactly."""
    k = next(i for i, t in enumerate(taken) if t not in TARGETS)
    assert taken[:k] == TARGETS[:k], "the moves before it are the file's"
    x, y, z = TARGETS[k - 1]
    assert taken[k] == pytest.approx((x, y, z + dz_mm)), "the step moves Z by the change"
    later = taken[k + 1:]
    after = [(x, y, z + dz_mm) for x, y, z in TARGETS[k:k + len(later)]]
    assert later and flat(later) == pytest.approx(flat(after)), "every later move shifted once"
    return k


def flat(targets: list[Target]) -> list[float]:
    return [value for target in targets for value in target]


async def playing(app: App) -> None:
    await app.kernel.jobs.save("zigzag.nc", JOB.encode())
    app.kernel.jobs.play("zigzag.nc")
    await app.clock.sleep(1.0)  # type: ignore[attr-defined]  # a few lines run, the rest wait


async def test_a_baby_step_runs_between_the_job_lines_and_shifts_every_later_move() -> None:
    async with running(make_config()) as app:
        taken = recording(app)
        await playing(app)
        jobs, interpreter = app.kernel.jobs, app.kernel.machine.interpreter
        answer = jobs.interject("M290 Z0.05", app.kernel.status.ticket())
        assert answer is not None
        assert interpreter.wco()[2] == 0.0, "asked for, not applied yet"
        assert await answer == []
        assert interpreter.wco()[2] == DZ_MM, "shown once applied"
        await jobs._task  # noqa: SLF001 - the player ends
        k = shifted_once_after(taken, DZ_MM)
        assert 1 < k < LINES and len(taken) == LINES + 1
        assert jobs.progress().state == "done"  # type: ignore[union-attr]
        assert app.kernel.machine.backend.steps[2] == round((TARGETS[-1][2] + DZ_MM) * 400)
        assert interpreter.wco()[2] == DZ_MM, "it stays after the job"
        assert interpreter.gc_report().startswith("[GC:G1 G54 G17 G21 G90"), "modes untouched"


async def test_a_stop_voids_a_waiting_baby_step() -> None:
    async with running(make_config()) as app:
        await playing(app)
        answer = app.kernel.jobs.interject("M290 Z0.05", app.kernel.status.ticket())
        assert answer is not None
        app.kernel.control.reset()
        try:
            outcome = await answer
        except CommandError as exc:
            assert exc.code == 45
        else:
            assert outcome is None, "the job ended before its turn: it did not run"
        assert app.kernel.machine.interpreter.wco()[2] == 0.0
        assert app.kernel.machine.interpreter.offsets_report()[-3].startswith("[G92:0.000,0")


async def test_a_job_abort_is_a_stop_and_a_baby_step_asked_before_it_never_runs() -> None:
    async with running(make_config()) as app:
        await playing(app)
        ticket = app.kernel.status.ticket()
        answer = app.kernel.jobs.interject("M290 Z0.05", ticket)
        assert answer is not None
        app.kernel.control.cancel_job()  # the UI's Stop, CANCEL_PRINT, Smoothie's abort
        assert not app.kernel.status.still_valid(ticket), "an abort voids what came before"
        assert await answer is None, "the job ended before its turn"
        with pytest.raises(CommandError) as refused:  # as SET_GCODE_OFFSET then runs it
            await app.kernel.dispatcher.submit("M290 Z0.05", SOURCE, ticket)
        assert refused.value.code == 45
        assert app.kernel.machine.interpreter.wco()[2] == 0.0


async def test_a_baby_step_beyond_the_travel_is_refused_and_the_job_goes_on_unshifted() -> None:
    async with running(make_config()) as app:
        taken = recording(app)
        await playing(app)
        answer = app.kernel.jobs.interject("M290 Z60", app.kernel.status.ticket())
        assert answer is not None
        with pytest.raises(CommandError) as refused:
            await answer
        assert refused.value.code == 15
        await app.kernel.jobs._task  # noqa: SLF001
        assert app.kernel.jobs.progress().state == "done"  # type: ignore[union-attr]
        assert taken == TARGETS


async def test_a_paused_job_applies_the_baby_step_when_it_resumes() -> None:
    async with running(make_config()) as app:
        taken = recording(app)
        await playing(app)
        app.kernel.control.hold()
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        answer = app.kernel.jobs.interject("M290 Z0.05", app.kernel.status.ticket())
        assert answer is not None
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert not answer.done() and app.kernel.machine.interpreter.wco()[2] == 0.0
        app.kernel.control.resume()
        assert await answer == []
        await app.kernel.jobs._task  # noqa: SLF001
        shifted_once_after(taken, DZ_MM)
        assert len(taken) == LINES + 1
        assert app.kernel.machine.backend.steps[2] == round((TARGETS[-1][2] + DZ_MM) * 400)


async def test_set_gcode_offset_through_the_api_socket_shifts_the_running_job(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), client(socket) as api:
        taken = recording(app)
        await app.kernel.jobs.save("zigzag.nc", JOB.encode())
        app.kernel.jobs.play("zigzag.nc")
        await asyncio.sleep(0.5)
        answer = await api.call("gcode/script", script="SET_GCODE_OFFSET Z_ADJUST=0.05 MOVE=1")
        assert answer["result"] == {}
        query = await api.call("objects/query", objects={"gcode_move": ["homing_origin"]})
        assert query["result"]["status"]["gcode_move"]["homing_origin"][2] == DZ_MM
        app.kernel.jobs.abort()  # the rest of the job is not needed
    k = shifted_once_after(taken, DZ_MM)
    assert 1 < k < LINES


async def test_in_a_pause_set_gcode_offset_answers_at_once_and_applies_at_resume(
        tmp_path: Path) -> None:
    async with served(tmp_path) as (app, socket), client(socket) as api:
        await api.call("gcode/subscribe_output", response_template={"tag": "out"})
        taken = recording(app)
        await app.kernel.jobs.save("zigzag.nc", JOB.encode())
        app.kernel.jobs.play("zigzag.nc")
        await asyncio.sleep(0.3)
        assert (await api.call("gcode/script", script="PAUSE"))["result"] == {}
        answer = await asyncio.wait_for(
            api.call("gcode/script", script="SET_GCODE_OFFSET Z_ADJUST=0.05 MOVE=1"), 1.0)
        assert answer["result"] == {}, "answered at once, not at Resume"
        await asyncio.sleep(0.3)
        assert app.kernel.machine.interpreter.wco()[2] == 0.0, "not applied in the pause"
        assert app.kernel.machine.stepgen.state.speed_mm_s == 0.0, "nothing moved"
        assert (await api.call("gcode/script", script="RESUME"))["result"] == {}
        for _ in range(100):
            if app.kernel.machine.interpreter.wco()[2] == DZ_MM:
                break
            await asyncio.sleep(0.02)
        await api.call("info")  # collects what was pushed meanwhile
        app.kernel.jobs.abort()
    said = [m["params"]["response"] for m in api.pushed if m.get("tag") == "out"]
    assert said[:2] == ["// SET_GCODE_OFFSET: the job is paused; the offset applies when it "
                        "resumes", "// SET_GCODE_OFFSET applied"], api.pushed
    shifted_once_after(taken, DZ_MM)
