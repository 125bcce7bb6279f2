"""One path for every line: module M-codes are interpreted with the line they are on, and the
live machine and the offline tools feed the same interpreter + planner."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from server.app import App
from server.backends.sim import SimBackend
from server.cli import main
from server.cli.offline import machine_interpreter
from server.errors import CommandError, ConfigError
from server.motion.moves import Action, Move
from server.motion.planner import Planner
from server.offline.estimate import estimate
from server.offline.stats import JobStats
from tests.conftest import CORPUS, make_config
from tests.support.helpers import running, submit_all

FAN = {"fan": {"on_mcode": 106, "off_mcode": 107}}
MODULE_JOB = [
    "G21 G90", "M3 S500", "G1 X10 F600 M106", "G1 Y10 M106 S128", "M107 G1 X20",
    "G0 X30 M106", "M221 S50", "G1 X40 Y20 F1200", "M42 P7 S255", "M107", "M5",
]


AXES_TOML = "".join(
    f"[axes.{axis}]\nsteps_per_mm = 80\nmax_rate_mm_s = 500\naccel_mm_s2 = 3000\nmax_mm = 300\n"
    for axis in "xy"
)


def fan_config() -> Any:
    return make_config(switch={**FAN, "light": {"pin": "P7"}}, laser={"pin": "laser"})


def sim(app: App) -> SimBackend:
    backend = app.kernel.machine.backend
    assert isinstance(backend, SimBackend)
    return backend


def record_planner(planner: Planner) -> list[tuple[Any, ...]]:
    """From now on, everything appended to ``planner``: moves and ordered actions."""
    seen: list[tuple[Any, ...]] = []
    append, append_action = planner.append, planner.append_action

    def on_move(move: Move) -> bool:  # as transparent as a recorder must be: the planner
        seen.append(_move_row(move))  # says whether it is full now (offer() acts on that)
        return append(move)

    def on_action(action: Action) -> None:
        seen.append(_action_row(action))
        append_action(action)

    planner.append = on_move  # type: ignore[method-assign]
    planner.append_action = on_action  # type: ignore[method-assign]
    return seen


def _move_row(move: Move) -> tuple[Any, ...]:
    actions = tuple(_action_row(action) for action in move.actions)
    return ("move", move.target_mm, move.feed_mm_s, move.kind, move.s_value, actions)


def _action_row(action: Action) -> tuple[Any, ...]:
    params = tuple(sorted((k, str(v)) for k, v in action.params.items()))
    return ("action", action.name, params, action.lead_s, action.stops_motion)


@pytest.mark.parametrize("line, x_mm", [
    ("G1 X10 F600 M106", 10.0), ("M107 G1 X20 F600", 20.0), ("G0 X30 M106", 30.0),
])
async def test_a_module_code_on_a_motion_line_moves_and_switches(line: str, x_mm: float) -> None:
    async with running(make_config(switch=FAN)) as app:
        fan_before = 0.0 if "M106" in line else 1.0
        if fan_before:
            await submit_all(app, ["M106"])
        assert await submit_all(app, [line]) == [[]]
        await app.kernel.machine.wait_idle()
        assert sim(app).position_mm()[0] == pytest.approx(x_mm)
        assert sim(app).output("fan") == 1.0 - fan_before


async def test_the_fan_switches_where_the_move_on_its_line_starts() -> None:
    async with running(make_config(switch=FAN)) as app:
        await submit_all(app, ["G1 X10 F600", "G1 X20 M106", "G1 X30 M107"])
        await app.kernel.machine.wait_idle()
        history = sim(app).history
        switched = [t for t, name, _ in sim(app).output_trace if name == "fan"]
        x_at = {round(t, 6): row[1] for row in history for t in (row[0],)}
        assert len(switched) == 2
        assert [x_at[round(t, 6)] for t in switched] == [pytest.approx(10.0, abs=0.05),
                                                         pytest.approx(20.0, abs=0.05)]


async def test_two_codes_of_one_switch_on_a_line_are_a_modal_group_violation() -> None:
    async with running(make_config(switch=FAN)) as app:
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["M106 M107"])
        assert info.value.code == 21


async def test_m42_without_its_pin_or_value_is_grbl_error_28() -> None:
    async with running(make_config(switch={"light": {"pin": "P7"}})) as app:
        for line in ("M42 S255", "M42 P7"):
            with pytest.raises(CommandError) as info:
                await submit_all(app, [line])
            assert info.value.code == 28, line


def test_two_modules_claiming_one_code_is_a_config_error_naming_both() -> None:
    config = make_config(switch={"fan": {"on_mcode": 106}, "air": {"on_mcode": 106}})
    with pytest.raises(ConfigError) as info:
        machine_interpreter(config)
    (problem,) = info.value.problems
    assert "M106" in problem and "[switch.fan]" in problem and "[switch.air]" in problem


def test_check_config_reports_a_code_claimed_twice(tmp_path: Path, capsys: Any) -> None:
    path = tmp_path / "two.toml"
    path.write_text(AXES_TOML + "[switch.fan]\non_mcode = 106\n[switch.air]\non_mcode = 106\n"
                    f"[jobs]\ndata_dir = '{tmp_path}'\n")
    assert main(["check-config", str(path)]) == 1
    assert "claimed by both [switch.fan] and [switch.air]" in capsys.readouterr().err


def test_estimate_runs_module_codes_as_the_server_does(tmp_path: Path, capsys: Any) -> None:
    path, job = tmp_path / "fan.toml", tmp_path / "job.gcode"
    path.write_text(AXES_TOML + "[switch.fan]\non_mcode = 106\noff_mcode = 107\n"
                    f"[jobs]\ndata_dir = '{tmp_path}'\n")
    job.write_text("G1 X10 F600 M106\nM107 G1 X20\nG0 X30 M106\nM107\n")
    assert main(["estimate", str(job), "--config", str(path), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "STOPPED" not in out and "lines" in out


async def live_sequence(config: Any, lines: list[str]) -> tuple[list[tuple[Any, ...]], int]:
    """What the live server appends to its planner for ``lines`` (virtual clock), and how
    many lines ran before the first refused one."""
    async with running(config) as app:
        seen = record_planner(app.kernel.machine.planner)
        ran = 0
        for line in lines:
            try:
                await submit_all(app, [line])
            except CommandError:
                break
            ran += 1
        await app.kernel.machine.wait_idle()
    return seen, ran


def offline_sequence(
    monkeypatch: pytest.MonkeyPatch, config: Any, lines: list[str]
) -> tuple[list[tuple[Any, ...]], JobStats]:
    """What ``estimate`` appends to its planner for ``lines``, and its result."""
    seen: list[tuple[Any, ...]] = []
    append, append_action, append_run = Planner.append, Planner.append_action, Planner.append_run

    def on_move(planner: Planner, move: Move) -> bool:
        seen.append(_move_row(move))
        return append(planner, move)

    def on_action(planner: Planner, action: Action) -> None:
        seen.append(_action_row(action))
        append_action(planner, action)

    def on_run(planner: Planner, moves: list[Move], *arrays: Any) -> int:
        taken = append_run(planner, moves, *arrays)
        seen.extend(map(_move_row, moves[:taken]))
        return taken

    monkeypatch.setattr(Planner, "append", on_move)
    monkeypatch.setattr(Planner, "append_action", on_action)
    monkeypatch.setattr(Planner, "append_run", on_run)
    stats = estimate(lines, config.core, interpreter=machine_interpreter(config))
    monkeypatch.undo()
    return seen, stats


# Lines of each corpus file compared: every file's kinds of line are in its first few thousand
# (the 626 KB raster repeats its scan lines: 40-190 s whole for the same comparison).
CORPUS_LINES = 4000


def _corpus() -> list[Path]:
    return sorted(p for p in CORPUS.iterdir() if p.suffix in (".gcode", ".nc"))


async def test_a_job_with_module_codes_plans_the_same_live_and_offline(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = fan_config()
    live, ran = await live_sequence(config, MODULE_JOB)
    offline, stats = offline_sequence(monkeypatch, config, MODULE_JOB)
    assert ran == len(MODULE_JOB) and stats.error is None
    switches = [row for row in live if row[0] == "action" and row[1] == "switch"]
    riding = [a for row in live if row[0] == "move" for a in row[5] if a[1] == "switch"]
    assert len(switches) + len(riding) == 6, "M106 x3, M107 x2 and M42: each one action"
    assert offline == live


@pytest.mark.slow
@pytest.mark.parametrize("path", _corpus(), ids=lambda p: p.name)
async def test_every_corpus_file_plans_the_same_live_and_offline(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = fan_config()
    lines = path.read_text(errors="replace").splitlines()[:CORPUS_LINES]
    live, ran = await live_sequence(config, lines)
    # The server stops at the first line it refuses (a soft limit, from where the job is placed,
    # or a bad line); the estimate reads a job whatever its placement (a soft limit is not its
    # business), so the two are compared on the lines the server ran.
    offline, stats = offline_sequence(monkeypatch, config, lines[:ran])
    assert stats.error is None and stats.lines == ran
    assert planned(offline) == planned(live)


def planned(rows: list[tuple[Any, ...]]) -> list[tuple[Any, ...]]:
    """What a plan depends on: the rows without follow spindle actions (a line's new S, which
    its move carries as ``s_value`` too; a plan reads its plain lines' moves without them)."""
    return [(*row[:5], tuple(a for a in row[5] if not _follows(a))) if row[0] == "move" else row
            for row in rows if not (row[0] == "action" and _follows(row))]


def _follows(row: tuple[Any, ...]) -> bool:
    return row[1] == "spindle" and row[3] == 0.0 and not row[4]
