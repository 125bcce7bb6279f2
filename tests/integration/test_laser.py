"""The [laser] module: power follows speed and S, rapids never fire, safety turns it off at once.

Every test runs a whole job on the virtual clock with the simulated backend. The laser samples
the motion state on its own 1 kHz timer, so the power the backend records at a tick is the one
computed from the motion state of the tick before (one sample period of PWM update lag); the
checks below compare each recorded power with the formula applied to the previous tick.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from modules.laser import LaserConfig
from server.app import App
from server.backends.sim import SimBackend
from server.config_loader import load_config
from server.errors import CommandError, ConfigError
from server.motion.motion_state import HoldState
from server.motion.moves import MoveKind, ToolMode
from tests.conftest import make_config
from tests.support.helpers import SOURCE, running, submit_all

PERIOD_S = 0.001
LASER = {"minimum_power": 0.1, "maximum_power": 0.8, "maximum_s_value": 1000}
POWER = -1  # history rows: (time_s, x, y, z, speed_mm_s, power)


def sim(app: App) -> SimBackend:
    """The simulated machine behind ``app`` (the default backend)."""
    backend = app.kernel.machine.backend
    assert isinstance(backend, SimBackend)
    return backend


def record_motion(app: App) -> list[tuple[Any, ...]]:
    """From now on, one motion snapshot per tick, aligned with ``backend.history``."""
    machine = app.kernel.machine
    backend, state = sim(app), machine.stepgen.state
    snapshots: list[tuple[Any, ...]] = []
    original = backend.sample

    def sample(time_s: float, position_mm: Any, speed_mm_s: float) -> None:
        original(time_s, position_mm, speed_mm_s)
        snapshots.append((time_s, state.speed_mm_s, state.nominal_mm_s, state.s_value,
                          state.tool_mode, state.kind, state.moving, state.hold))

    backend.history.clear()
    backend.sample = sample  # type: ignore[method-assign]
    return snapshots


def expected_power(snapshot: tuple[Any, ...], low: float = 0.1, high: float = 0.8,
                   scale: float = 1.0, max_s: float = 1000.0) -> float:
    """The issue's formula, written out independently of the module."""
    _, speed, nominal, s, mode, kind, moving, hold = snapshot
    if not moving or hold is not HoldState.NONE or s <= 0 or mode is ToolMode.OFF:
        return 0.0
    if kind not in (MoveKind.FEED, MoveKind.ARC):
        return 0.0
    ratio = s / max_s * scale * (speed / nominal if mode is ToolMode.CCW else 1.0)
    return min(high, max(0.0, low + (high - low) * ratio))


def laser_trace(app: App) -> list[tuple[float, float]]:
    return [(t, v) for t, name, v in sim(app).output_trace if name == "laser"]


def raster_lines() -> list[str]:
    lines = ["G0 X5 Y5", "M4", "F3000"]
    for k in range(20):
        s = 100 + k * 900 / 19
        lines.append(f"G1 X{5 + 0.5 * (k + 1):.1f} S{s:.2f}")
    return [*lines, "M5", "G0 X0 Y0"]


async def test_raster_power_follows_speed_and_s_at_every_sample() -> None:
    async with running(make_config(laser=LASER)) as app:
        snapshots = record_motion(app)
        await submit_all(app, raster_lines())
        await app.kernel.machine.wait_idle()
        history = list(sim(app).history)
    assert len(history) == len(snapshots) > 200
    for row, before in zip(history[1:], snapshots, strict=False):
        expected = expected_power(before)
        assert row[POWER] == pytest.approx(expected, rel=0.01, abs=1e-9), (row, before)
    rapids = [row for row, now, before in zip(history[1:], snapshots[1:], snapshots, strict=False)
              if now[5] is before[5] is MoveKind.RAPID and now[6]]
    assert len(rapids) > 50 and all(row[POWER] == 0.0 for row in rapids), "rapids never fire"
    ramp = [(row, before) for row, before in zip(history[1:], snapshots, strict=False)
            if before[5] is MoveKind.FEED and before[6] and 0 < before[1] < 0.9 * before[2]]
    assert len(ramp) >= 10, "accelerating and decelerating samples exist"
    at_nominal = [expected_power((b[0], b[2], *b[2:])) for _, b in ramp]
    assert all(row[POWER] < full for (row, _), full in zip(ramp, at_nominal, strict=True)), \
        "power is scaled down while the speed is below nominal"


async def test_motion_never_stops_between_raster_segments_with_different_s() -> None:
    async with running(make_config(laser=LASER)) as app:
        record_motion(app)
        await submit_all(app, raster_lines())
        await app.kernel.machine.wait_idle()
        history = list(sim(app).history)
    cut = [row for row in history if row[2] == 5.0 and 5.0 < row[1] < 15.0]
    assert all(row[4] > 0.0 for row in cut)
    for k in range(1, 20):
        boundary = 5.0 + 0.5 * k
        crossing = next(row for row in cut if row[1] >= boundary)
        if boundary < 14.5:  # the last segment holds the deceleration
            assert crossing[4] == pytest.approx(50.0, rel=0.01), f"full speed at X{boundary}"


async def test_constant_power_in_m3_ignores_speed_unless_proportional() -> None:
    for proportional, expect_ramp in ((False, False), (True, True)):
        config = make_config(laser={**LASER, "proportional_power": proportional})
        async with running(config) as app:
            snapshots = record_motion(app)
            await submit_all(app, ["M3 S500", "G1 X2 F3000", "M5"])
            await app.kernel.machine.wait_idle()
            history = list(sim(app).history)
        powers = {round(row[POWER], 9) for row, before in zip(history[1:], snapshots,
                                                              strict=False) if before[6]}
        assert (len(powers - {0.0}) > 1) is expect_ramp
        assert max(powers) == pytest.approx(0.1 + 0.7 * 0.5)


async def test_m5_after_g1_turns_laser_off_only_when_the_move_ends() -> None:
    async with running(make_config(laser={"ttl_pin": "laser_enable"})) as app:
        snapshots = record_motion(app)
        await submit_all(app, ["M3", "G1 X10 S500 F600", "M5", "G0 X0"])
        await app.kernel.machine.wait_idle()
        history = list(sim(app).history)
        trace = laser_trace(app)
        ttl = [(t, v) for t, name, v in sim(app).output_trace
               if name == "laser_enable"]
    feed = [i for i, snap in enumerate(snapshots) if snap[5] is MoveKind.FEED and snap[6]]
    first, last = feed[0], feed[-1]
    assert feed == list(range(first, last + 1))
    assert all(row[POWER] == 0.5 for row in history[first + 1 : last + 1]), "on through the G1"
    end_s = (history[last][0], history[last + 1][0])  # the G1 ends between these two ticks
    (on_s, on), (off_s, off) = trace
    assert (on, off) == (0.5, 0.0)
    assert end_s[0] < off_s <= end_s[1] + PERIOD_S + 1e-9, "off within one sample of the end"
    assert all(row[POWER] == 0.0 for row in history[last + 2 :]), "off during the G0"
    assert ttl == [(on_s, 1.0), (off_s, 0.0)], "the TTL enable follows the firing"


async def test_feed_hold_turns_the_laser_off_at_once_and_resume_brings_it_back() -> None:
    async with running(make_config(laser={})) as app:
        machine, clock = app.kernel.machine, app.clock
        await submit_all(app, ["M4 S800", "G1 X30 F600"])
        await clock.sleep(1.0)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.8)
        hold_s = clock.now_s()
        machine.feed_hold()
        assert sim(app).output("laser") == 0.0
        assert laser_trace(app)[-1] == (hold_s, 0.0), "off at the same virtual time as the hold"
        await clock.sleep(0.5)  # type: ignore[attr-defined]
        held = [row for row in sim(app).history if row[0] > hold_s]
        assert held[-1][4] == 0.0, "motion stopped"
        assert all(row[POWER] == 0.0 for row in held), "off while decelerating and stopped"
        machine.cycle_start()
        await clock.sleep(0.1)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.8), "back with the motion"
        await machine.wait_idle()
        assert sim(app).output("laser") == 0.0


async def test_after_resume_dynamic_power_ramps_up_from_standstill() -> None:
    async with running(make_config(laser={})) as app:
        machine, clock = app.kernel.machine, app.clock
        await submit_all(app, ["M4 S1000", "G1 X30 F600"])
        await clock.sleep(1.0)  # type: ignore[attr-defined]
        machine.feed_hold()
        await clock.sleep(0.5)  # type: ignore[attr-defined]
        resume_s = clock.now_s()
        machine.cycle_start()
        await clock.sleep(0.01)  # type: ignore[attr-defined]
        after = [row for row in sim(app).history if row[0] > resume_s]
        assert 0.0 < after[1][POWER] < 0.9, "the power ramps up with the speed"


@pytest.mark.parametrize("how", ["M112", "kernel.alarm"])
async def test_a_halt_mid_job_turns_the_laser_off_at_once_and_locks_gcode(how: str) -> None:
    async with running(make_config(laser={})) as app:
        kernel, clock = app.kernel, app.clock
        await submit_all(app, ["M3 S600", "G1 X30 F600"])
        await clock.sleep(0.5)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.6)
        halt_s = clock.now_s()
        if how == "M112":
            await kernel.dispatcher.submit("M112", SOURCE)
        else:
            kernel.alarm(1, "hard limit")
        assert sim(app).output("laser") == 0.0
        assert laser_trace(app)[-1] == (halt_s, 0.0)
        with pytest.raises(CommandError) as info:
            await kernel.dispatcher.submit("G1 X5", SOURCE)
        assert info.value.code == 9
        await clock.sleep(0.2)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == 0.0
        assert await submit_all(app, ["$X", "G1 X5 F600"]) == [[], []]


async def test_spindle_override_and_m221_scale_the_power() -> None:
    async with running(make_config(laser={})) as app:
        machine, clock = app.kernel.machine, app.clock
        await submit_all(app, ["M221 S50", "M3 S800", "G1 X30 F600"])
        await clock.sleep(0.5)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.4)
        machine.set_overrides(spindle=150)
        await clock.sleep(0.01)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.6)
        assert app.kernel.modules["laser"].status()["scale"] == pytest.approx(0.75)
        assert await submit_all(app, ["M221"]) == [["[MSG:laser power scale 50%]"]]


async def test_m221_s_after_m3_scales_the_power_and_leaves_the_spindle_speed() -> None:
    """M221's S is its percentage (as Marlin's): the laser's S stays what M3 set."""
    async with running(make_config(laser={})) as app:
        await submit_all(app, ["M3 S800", "M221 S50", "G1 X30 F600"])
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == pytest.approx(0.4)
        assert " S800" in app.kernel.machine.interpreter.gc_report()


async def test_fire_works_while_idle_only_and_stops_by_itself() -> None:
    async with running(make_config(laser={"fire_max_duration_s": 2})) as app:
        machine, clock = app.kernel.machine, app.clock
        assert await submit_all(app, ["fire 50"]) == [["[MSG:fire 50% for at most 2s]"]]
        await clock.sleep(1.0)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == 0.5, "fires while idle, not moving"
        assert await submit_all(app, ["fire off"]) == [["[MSG:fire off]"]]
        assert sim(app).output("laser") == 0.0
        await submit_all(app, ["fire 20"])
        await clock.sleep(2.5)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == 0.0, "capped by fire_max_duration_s"
        await submit_all(app, ["fire 20"])
        machine.soft_reset()
        await clock.sleep(0.002)  # type: ignore[attr-defined]
        assert sim(app).output("laser") == 0.0, "Ctrl-X stops it"
        await submit_all(app, ["G1 X30 F600"])
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["fire 10"])
        assert info.value.code == 45


@pytest.mark.parametrize(("laser", "expected"), [
    ({"pin": "bad pin"}, "[laser] pin: String should match pattern"),
    ({"maximum_power": 1.5}, "[laser] maximum_power: Input should be less than or equal to 1"),
    ({"minimum_power": 0.5, "maximum_power": 0.2},
     "[laser]: minimum_power must not exceed maximum_power"),
    ({"maximum_s_value": 0}, "[laser] maximum_s_value: Input should be greater than 0"),
    ({"power": 1}, "[laser] power: unknown key"),
    ({"one": {"pin": "a"}}, "[laser.one]: unknown key"),  # [laser] takes no instances
])
def test_bad_laser_config_names_the_section_and_key(laser: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        make_config(laser=laser)
    assert any(problem.startswith(f"test.toml: {expected}") for problem in info.value.problems), \
        info.value.problems


def test_the_sample_rate_is_capped_by_the_pwm_frequency() -> None:
    assert LaserConfig().period_s == pytest.approx(0.001)
    assert LaserConfig(pwm_frequency_hz=200).period_s == pytest.approx(0.005)


def test_a_section_configured_twice_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "machine.toml"
    path.write_text('[axes.x]\nsteps_per_mm = 80\nmax_rate_mm_s = 100\naccel_mm_s2 = 100\n'
                    'max_mm = 100\n[laser]\npin = "a"\n[laser]\npin = "b"\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    (problem,) = info.value.problems
    assert str(path) in problem and "('laser',) twice" in problem
