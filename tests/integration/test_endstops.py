"""The [endstops] module: homing ($H, G28.2), its alarms, hard limits, M119 and Pn:."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

import pytest

from server.app import App
from server.backends.sim import SimBackend
from server.config import Config
from server.errors import CommandError, ConfigError
from server.kernel.status import snapshot
from server.runtime.clock import VirtualClock
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running, submit_all

AXES = {
    "x": {"direction": "min", "switch_at_mm": -3.0, "order": 2},
    "y": {"direction": "min", "switch_at_mm": -2.0, "order": 2},
    "z": {"direction": "max", "switch_at_mm": 3.0, "order": 1, "seek_mm_s": 10,
          "feed_mm_s": 2, "pull_off_mm": 1},
}
STEP_MM = 1 / 80  # one X/Y step: the sim reports positions in whole steps


def sim(app: App) -> SimBackend:
    """The simulated machine behind ``app`` (the default backend)."""
    backend = app.kernel.machine.backend
    assert isinstance(backend, SimBackend)
    return backend


def endstops(**axes: dict[str, Any]) -> dict[str, Any]:
    merged = {name: {**AXES[name], **axes.get(name, {})} for name in AXES}
    return {"axes": {name: body for name, body in merged.items() if body is not None}}


def record(app: App, event: str) -> list[Any]:
    seen: list[Any] = []
    app.kernel.events.subscribe(event, lambda *args: seen.append(args[0] if args else None))
    return seen


async def test_homing_sets_the_machine_position_with_the_travel_off_the_switches() -> None:
    async with running(make_config(endstops=endstops())) as app:
        kernel = app.kernel
        states = record(app, "state")
        assert await submit_all(app, ["G1 X20 Y10 F3000", "$H"]) == [[], ["[MSG:Homed XYZ]"]]
        assert kernel.machine.stepgen.state.position_mm == (0.0, 0.0, 50.0)
        physical = sim(app).position_mm()
        assert physical == pytest.approx((-3 + 2, -2 + 2, 3 - 1), abs=2 * STEP_MM)
        assert MachineState.HOME in states and kernel.state is MachineState.IDLE
        assert await submit_all(app, ["M114"]) == [
            ["C: X:0.0000 Y:0.0000 Z:50.0000 E:0.0000 MPos: X:0.0000 Y:0.0000 Z:50.0000"]]
        assert await submit_all(app, ["G0 X10 Y5 Z-10"]) == [[]], "inside the soft limits"
        await kernel.machine.wait_idle()
        assert kernel.state is MachineState.IDLE


async def test_homing_runs_the_groups_in_order_z_first() -> None:
    async with running(make_config(endstops=endstops())) as app:
        await submit_all(app, ["G1 X20 Y10 F3000"])
        await app.kernel.machine.wait_idle()
        start_s = app.clock.now_s()
        await submit_all(app, ["$H"])
        rows = [row for row in sim(app).history if row[0] > start_s]
        pairs = list(zip(rows, rows[1:], strict=False))  # moves only: not the re-homed jump
        z_done_s = max(b[0] for a, b in pairs if 0 < abs(a[3] - b[3]) < 1)
        x_start_s = min(b[0] for a, b in pairs if 0 < abs(a[1] - b[1]) < 1)
        assert z_done_s < x_start_s


async def test_g28_2_homes_only_the_named_axes() -> None:
    async with running(make_config(endstops=endstops())) as app:
        await submit_all(app, ["G1 X20 Y10 F3000", "G28.2 X0"])
        assert app.kernel.machine.stepgen.state.position_mm == (0.0, 10.0, 0.0)
        assert app.kernel.modules["endstops"].status()["homed"] == ["X"]
        assert await submit_all(app, ["$HY"]) == [["[MSG:Homed Y]"]]


async def test_homing_with_a_missing_switch_raises_alarm_9() -> None:
    config = make_config(endstops=endstops(y={"switch_at_mm": None}))
    async with running(config) as app:
        pushed = record(app, "push")
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["$H"])
        assert info.value.code == 9
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 9
        assert "ALARM:9" in pushed and any("y_min switch not found" in p for p in pushed)
        assert not app.kernel.machine.stepgen.state.moving


async def test_a_switch_that_does_not_clear_on_pull_off_raises_alarm_8() -> None:
    async with running(make_config(endstops=endstops())) as app:
        backend = sim(app)
        backend.switch_triggered = lambda name: name == "z_max"  # type: ignore
        with pytest.raises(CommandError):
            await submit_all(app, ["$H"])
        assert app.kernel.alarm_code == 8


async def test_a_reset_during_homing_raises_alarm_6() -> None:
    async with running(make_config(endstops=endstops())) as app:
        kernel = app.kernel
        homing = asyncio.create_task(submit_all(app, ["G1 X50 F6000", "$H"]))
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert kernel.state is MachineState.HOME
        kernel.machine.soft_reset()
        with pytest.raises(CommandError):
            await homing
        assert kernel.state is MachineState.ALARM and kernel.alarm_code == 6
        assert not kernel.machine.stepgen.state.moving


async def test_homing_is_allowed_in_alarm_and_unlocks_the_machine() -> None:
    async with running(make_config(endstops=endstops())) as app:
        app.kernel.alarm(1, "hard limit")
        with pytest.raises(CommandError):
            await submit_all(app, ["G0 X5"])
        assert await submit_all(app, ["$H", "G0 X5"]) == [["[MSG:Homed XYZ]"], []]


async def test_a_limit_switch_hit_during_a_job_raises_alarm_1_and_halts() -> None:
    config = make_config(endstops=endstops(x={"direction": "max", "switch_at_mm": 150}))
    async with running(config) as app:
        kernel = app.kernel
        await submit_all(app, ["G1 X300 F6000"])
        await app.clock.sleep(5.0)  # type: ignore[attr-defined]
        assert kernel.state is MachineState.ALARM and kernel.alarm_code == 1
        x_mm = kernel.machine.stepgen.state.position_mm[0]
        assert 150 <= x_mm < 150 + 100 * 0.002, "stopped within two ticks at 100 mm/s"
        assert not kernel.machine.stepgen.state.moving
        assert await submit_all(app, ["$X", "G1 X100 F6000"]) == [[], []]
        await kernel.machine.wait_idle()
        assert kernel.state is MachineState.IDLE, "jogging off a pressed switch is allowed"


async def test_m119_and_the_status_pins_report_active_switches() -> None:
    async with running(make_config(endstops=endstops())) as app:
        assert await submit_all(app, ["M119"]) == [["X_min:0 Y_min:0 Z_max:0"]]
        sim(app).switches_at_mm["y_min"] = 0.0
        assert await submit_all(app, ["M119"]) == [["X_min:0 Y_min:1 Z_max:0"]]
        assert snapshot(app.kernel, 0).pins == "Y"
        app.kernel.alarm(10, "stop")
        assert await submit_all(app, ["M119"]) == [["X_min:0 Y_min:1 Z_max:0"]], "in alarm too"


@pytest.mark.parametrize(("axes", "expected"), [
    ({"x": {"direction": "left"}}, "[endstops.axes.x] direction: Input should be 'min' or 'max'"),
    ({"x": {"pull_off_mm": 0}}, "[endstops.axes.x] pull_off_mm: Input should be greater than 0"),
    ({"x": {"seek": 5}}, "[endstops.axes.x] seek: unknown key"),
    ({}, "[endstops.axes]: Dictionary should have at least 1 item"),
])
def test_bad_endstops_config_names_the_section_and_key(axes: dict[str, Any],
                                                       expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        make_config(endstops={"axes": axes})
    assert any(p.startswith(f"test.toml: {expected}") for p in info.value.problems), \
        info.value.problems


def test_an_endstop_on_an_axis_the_machine_lacks_is_a_config_error() -> None:
    with pytest.raises(ConfigError) as info:
        App(make_config(endstops={"axes": {"a": {}}}), clock=VirtualClock())
    assert info.value.problems == ["[endstops.axes.a]: no such axis (axes: X, Y, Z)"]


def homed(app: App) -> list[str]:
    return list(app.kernel.modules["endstops"].status()["homed"])


async def test_homing_is_lost_at_motors_off_an_emergency_stop_and_a_reset_in_motion() -> None:
    async with running(make_config(endstops=endstops())) as app:
        for lose in (["M84"], ["M112"]):
            await submit_all(app, ["$H"])
            assert homed(app) == ["X", "Y", "Z"]
            with contextlib.suppress(CommandError):
                await submit_all(app, lose)
            await app.kernel.machine.wait_idle()
            assert homed(app) == [], lose
        await submit_all(app, ["$H", "G1 X200 F600"])
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        app.kernel.control.reset()  # Ctrl-X while moving: ALARM:3
        assert app.kernel.alarm_code == 3 and homed(app) == []
        await submit_all(app, ["$H", "$SLP"])
        assert homed(app) == []


async def test_homing_is_kept_by_a_soft_limit_alarm_and_a_reset_at_rest() -> None:
    async with running(make_config(endstops=endstops())) as app:
        await submit_all(app, ["$H"])
        with pytest.raises(CommandError):
            await submit_all(app, ["G1 X5000 F600"])
        assert app.kernel.alarm_code == 2 and homed(app) == ["X", "Y", "Z"]
        await submit_all(app, ["$X"])
        app.kernel.control.reset()
        assert homed(app) == ["X", "Y", "Z"]


async def test_grbls_homing_settings_act_on_the_endstops_and_are_kept_across_a_restart(
        tmp_path: Path) -> None:
    """``$23``-``$27`` (Grbl 1.1h's homing settings) read and write the [endstops] section;
    written values are saved and adopted again by the next start; ``$22=0`` refuses ``$H``."""
    def config() -> Config:  # each start reads its config anew, in the same data folder
        return make_config(endstops=endstops(), jobs={"data_dir": str(tmp_path)})

    async with running(config()) as app:
        listed = (await submit_all(app, ["$$"]))[0]
        assert [line for line in listed if line[:4] in ("$22=", "$23=", "$24=", "$27=")] == [
            "$22=1", "$23=3", "$24=120.000", "$27=1.000"]  # X, Y home to min; slowest; least
        await submit_all(app, ["$24=90", "$25=1200", "$26=100", "$27=1.5", "$23=4"])
        module = app.kernel.modules["endstops"]
        axes = module.config.axes  # type: ignore[attr-defined]
        assert {axis.feed_mm_s for axis in axes.values()} == {1.5}
        assert {axis.seek_mm_s for axis in axes.values()} == {20.0}
        assert {axis.pull_off_mm for axis in axes.values()} == {1.5}
        assert [axes[name].direction for name in "xyz"] == ["max", "max", "min"]
        assert module.config.debounce_s == 0.1  # type: ignore[attr-defined]
        await submit_all(app, ["$22=0"])
        with pytest.raises(CommandError) as refused:
            await submit_all(app, ["$H"])
        assert refused.value.code == 5
    async with running(config()) as app:
        values = app.kernel.machine.settings.values()
        assert (values[22], values[23], values[24], values[26]) == (0, 4, 90.0, 100)
