"""A stored job reads its runs of plain lines in spans (``Dispatcher.begin_span``, the
machine's ``handle_span``): the planner gets exactly what the job's lines one by one give it,
follow actions and all, whether the planner had room for a whole span or for a few lines at a
time; the job ends where it would line by line; a stop while a span waits for room ends it
and nothing more is queued; a refused line amid a span stops the job at that line."""

from __future__ import annotations

import asyncio
import random
from typing import Any

import pytest

from server.app import App
from server.gcode.plain import PlainSpan
from server.machine.feed import GcodeFeed
from server.machine.machine import Machine
from server.motion.moves import Action
from tests.conftest import make_config
from tests.support.helpers import running

LINES = 400
BAD = "G1 X5 F0"


def job(seed: int, bad_at: int | None = None) -> str:
    """Plain lines inside the travel (G0/G1, X/Y, a new F or S now and then, an S alone),
    a G91 stretch and a dwell (the one-line path's) in between; ``bad_at``: that line is a
    G1 at feed 0 (error 22 when it runs; the job's fit is no matter)."""
    rng = random.Random(seed)
    lines = ["G21 G90 G94 M3 S0 F3000"]
    for number in range(2, LINES + 1):
        if number == bad_at:
            lines.append(BAD)
        elif number % 97 == 0:
            lines += ["G91", "G1 X1 Y1", "G1 X-1 Y-1", "G90", "G4 P0.01"]
        elif rng.random() < 0.05:
            lines.append(f"S{rng.randrange(0, 1000)}")
        else:
            words = [rng.choice(["G1", "G0", ""]), f"X{rng.uniform(0, 6):.3f}",
                     f"Y{rng.uniform(0, 6):.3f}"]
            if rng.random() < 0.3:
                words.append(f"S{rng.randrange(0, 1000)}")
            if rng.random() < 0.05:
                words.append(f"F{rng.choice([600, 1500, 6000])}")
            lines.append(" ".join(word for word in words if word))
    return "\n".join(lines) + "\n"


def recording(app: App) -> list[Any]:
    """Every move and action the planner takes, in order (the real planner still plans it)."""
    planner, taken = app.kernel.machine.planner, []
    append, append_action = planner.append, planner.append_action

    def append_move(move):  # type: ignore[no-untyped-def]
        taken.append(move)
        return append(move)

    def append_an_action(action: Action) -> None:
        taken.append(action)
        append_action(action)

    planner.append = append_move  # type: ignore[method-assign]
    planner.append_action = append_an_action  # type: ignore[method-assign]
    return taken


async def played(text: str, spans: bool, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """What playing ``text`` gave the planner, how the job ended and where, and how many
    spans were read (and read on from where they were)."""
    readings = {"read": 0, "fresh": 0}
    read_afresh, read_span = PlainSpan.read, GcodeFeed._read_span  # noqa: SLF001

    def counted_afresh(self, run):  # type: ignore[no-untyped-def]
        readings["fresh"] += 1
        read_afresh(self, run)

    def counted_read(self, span):  # type: ignore[no-untyped-def]
        readings["read"] += 1
        return read_span(self, span)

    with monkeypatch.context() as patch:
        patch.setattr(Machine, "reads_spans", spans)
        patch.setattr(PlainSpan, "read", counted_afresh)
        patch.setattr(GcodeFeed, "_read_span", counted_read)
        async with running(make_config()) as app:
            taken = recording(app)
            jobs, machine = app.kernel.jobs, app.kernel.machine
            await jobs.save("spans.nc", text.encode())
            jobs.play("spans.nc")
            await jobs._task  # noqa: SLF001 - the player ends
            progress = jobs.progress()
            assert progress is not None
            return {"taken": repr(taken), "state": progress.state, "error": progress.error,
                    "lines": progress.lines_done, "interpreter": repr(machine.interpreter.save()),
                    "position": machine.stepgen.state.position_mm, **readings}


@pytest.mark.parametrize("seed", range(3))
async def test_a_job_in_spans_gives_the_planner_what_its_lines_one_by_one_give(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = job(seed)
    alone = await played(text, spans=False, monkeypatch=monkeypatch)
    spans = await played(text, spans=True, monkeypatch=monkeypatch)
    assert alone["fresh"] == alone["read"] == 0, "line by line"
    assert spans["fresh"] >= 2, "spans were read"
    assert spans["read"] > 2 * spans["fresh"], "spans were read on as the planner had room"
    for key in ("taken", "state", "error", "lines", "interpreter", "position"):
        assert spans[key] == alone[key], key
    assert spans["state"] == "done" and spans["lines"] == text.count("\n")


async def test_a_refused_line_amid_a_span_stops_the_job_at_that_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = job(7, bad_at=150)
    number = text.splitlines().index(BAD) + 1
    alone = await played(text, spans=False, monkeypatch=monkeypatch)
    spans = await played(text, spans=True, monkeypatch=monkeypatch)
    assert spans["fresh"] >= 2, "spans were read, before the line and after the G91 stretch"
    assert spans["state"] == "failed" and spans["error"].startswith(f"line {number}: error:22")
    for key in ("taken", "error", "lines", "interpreter"):
        assert spans[key] == alone[key], key


async def test_a_stop_while_a_span_waits_for_room_ends_the_job_and_queues_nothing_more() -> None:
    """(The job is M3 with a new S now and then: the stop leaves the tool off, M5.)"""
    async with running(make_config()) as app:
        taken = recording(app)
        jobs, machine = app.kernel.jobs, app.kernel.machine
        await jobs.save("spans.nc", job(3).encode())
        jobs.play("spans.nc")
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        while not machine.planner.is_full():  # the job's span waits for room
            await app.clock.sleep(0.001)  # type: ignore[attr-defined]
        assert jobs.progress().state == "running" and 0 < len(taken) < LINES  # type: ignore[union-attr]
        before = len(taken)
        assert " M3 " in machine.interpreter.gc_report()
        app.kernel.control.reset()  # Ctrl-X: the player is cancelled where it waits
        await asyncio.wait({jobs._task})  # noqa: SLF001
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert len(taken) == before, "nothing queued after the stop"
        progress = jobs.progress()
        assert progress is not None and progress.state in ("failed", "aborted")
        assert not machine.stepgen.state.moving and len(machine.planner) == 0
        assert machine.interpreter.position == machine.stepgen.state.position_mm
        modal = machine.interpreter.gc_report()
        assert " M5 " in modal and modal.endswith(" S0]"), "the tool off in the modal state"
