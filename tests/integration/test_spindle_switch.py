"""The [spindle] and [switch.NAME] modules: outputs change in order with motion, never early."""

from __future__ import annotations

from typing import Any

import pytest

from modules.spindle import SpindleConfig, spindle_pwm
from server.app import App
from server.backends.sim import SimBackend
from server.errors import CommandError, ConfigError
from server.motion.moves import ToolMode
from server.protocol.events import Realtime
from tests.conftest import make_config
from tests.support.helpers import running, submit_all

FAN = {"fan": {"on_mcode": 106, "off_mcode": 107}}
TICK_S = 0.001
SPINDLE = {"min_rpm": 100, "max_rpm": 1000, "min_pwm": 0.1, "max_pwm": 1.0}


def sim(app: App) -> SimBackend:
    """The simulated machine behind ``app`` (the default backend)."""
    backend = app.kernel.machine.backend
    assert isinstance(backend, SimBackend)
    return backend


def trace(app: App, pin: str) -> list[tuple[float, float]]:
    return [(t, v) for t, name, v in sim(app).output_trace if name == pin]


def record_block_ends(app: App) -> list[float]:
    """From now on, the time of every tick during which a block ended (the move end times)."""
    machine = app.kernel.machine
    backend, state = sim(app), machine.stepgen.state
    ends: list[float] = []
    done = [state.blocks_done]
    original = backend.sample

    def sample(time_s: float, position_mm: Any, speed_mm_s: float) -> None:
        original(time_s, position_mm, speed_mm_s)
        if state.blocks_done != done[0]:
            done[0] = state.blocks_done
            ends.append(time_s)

    backend.sample = sample  # type: ignore[method-assign]
    return ends


async def run_job(app: App, lines: list[str]) -> None:
    await submit_all(app, lines)
    await app.kernel.machine.wait_idle()


@pytest.mark.parametrize(("mode", "rpm", "pwm"), [
    (ToolMode.CW, 0, 0.0), (ToolMode.CW, 50, 0.1), (ToolMode.CW, 100, 0.1),
    (ToolMode.CCW, 550, 0.55), (ToolMode.CW, 1000, 1.0), (ToolMode.CW, 5000, 1.0),
    (ToolMode.OFF, 500, 0.0),
])
def test_spindle_maps_rpm_to_pwm_like_grbl(mode: ToolMode, rpm: float, pwm: float) -> None:
    assert spindle_pwm(SpindleConfig(**SPINDLE), mode, rpm) == pytest.approx(pwm)


async def test_spindle_starts_exactly_when_motion_reaches_m3() -> None:
    async with running(make_config(spindle=SPINDLE)) as app:
        ends = record_block_ends(app)
        await submit_all(app, ["G1 X10 F600", "M3 S550", "G1 X20"])
        assert sim(app).output("spindle") == 0.0, "not when received"
        await app.kernel.machine.wait_idle()
        assert trace(app, "spindle") == [(ends[0], pytest.approx(0.55))]
        assert app.kernel.modules["spindle"].status()["rpm"] == 550


async def test_spindle_override_scales_the_rpm_and_m5_stops_it() -> None:
    async with running(make_config(spindle=SPINDLE)) as app:
        machine = app.kernel.machine
        await run_job(app, ["M4 S500"])
        assert sim(app).output("spindle") == pytest.approx(0.1 + 0.9 * 400 / 900)
        machine.set_overrides(spindle=200)
        assert sim(app).output("spindle") == 1.0
        await run_job(app, ["M5"])
        assert sim(app).output("spindle") == 0.0


async def test_spindle_keeps_turning_in_feed_hold_unless_spindle_stop_is_sent() -> None:
    async with running(make_config(spindle=SPINDLE)) as app:
        machine, clock = app.kernel.machine, app.clock
        await submit_all(app, ["M3 S1000", "G1 X30 F600"])
        await clock.sleep(0.5)  # type: ignore[attr-defined]
        machine.feed_hold()
        await clock.sleep(0.2)  # type: ignore[attr-defined]
        assert sim(app).output("spindle") == 1.0, "Grbl keeps the spindle on in hold"
        machine.realtime(Realtime.SPINDLE_STOP)
        assert sim(app).output("spindle") == 0.0
        machine.cycle_start()
        assert sim(app).output("spindle") == 1.0, "restored on resume"
        app.kernel.alarm(10, "stop")
        assert sim(app).output("spindle") == 0.0, "off at once on halt"


async def test_spin_up_delay_makes_motion_wait_for_the_spindle() -> None:
    config = make_config(spindle={**SPINDLE, "spin_up_delay_s": 0.5})
    async with running(config) as app:
        ends = record_block_ends(app)
        await run_job(app, ["M3 S1000", "G1 X10 F600", "M3 S800", "G1 X20", "M5", "M3",
                            "G1 X30"])
        history = list(sim(app).history)
        ((on_s, _), (change_s, _), (off_s, _), (again_s, _)) = trace(app, "spindle")
    first_move_s = next(row[0] for row in history if row[1] > 0.0)
    assert first_move_s >= on_s + 0.5 - TICK_S, "the dwell starts with the spindle"
    assert change_s == ends[1], "a speed change while on does not wait"
    restart_s = next(row[0] for row in history if row[1] > 20.0)
    assert off_s == again_s, "M5 then M3 with no motion between: one tick"
    assert restart_s >= again_s + 0.5 - TICK_S, "starting again after M5 waits again"


async def test_fan_comes_on_exactly_when_the_first_move_ends() -> None:
    async with running(make_config(switch=FAN)) as app:
        ends = record_block_ends(app)
        await submit_all(app, ["G1 X10 F600", "M106 S255"])
        assert sim(app).output("fan") == 0.0, "not when the line arrives"
        await submit_all(app, ["G1 X20", "M106 S128", "G1 X30", "M107", "G1 X40"])
        await app.kernel.machine.wait_idle()
        assert trace(app, "fan") == [(ends[0], 1.0), (ends[1], pytest.approx(128 / 255)),
                                     (ends[2], 0.0)], "each exactly when the move before ends"
        assert app.kernel.modules["switch.fan"].status() == {
            "pin": "fan", "value": 0.0, "on": False, "on_gcode": "M106", "off_gcode": "M107",
            "level_gcode": "M106 S", "max_s": 255.0}


async def test_a_coolant_switch_follows_m8_and_m9_in_order_and_the_realtime_toggle() -> None:
    config = make_config(switch={"air": {"on_mcode": 8, "off_mcode": 9}, **FAN})
    async with running(config) as app:
        machine = app.kernel.machine
        ends = record_block_ends(app)
        await run_job(app, ["G1 X10 F600", "M8", "G1 X20", "M9", "G1 X30"])
        assert trace(app, "air") == [(ends[0], 1.0), (ends[1], 0.0)]
        machine.realtime(Realtime.FLOOD)
        assert sim(app).output("air") == 1.0, "0xA0 toggles flood at once"
        machine.realtime(Realtime.MIST)
        assert sim(app).output("air") == 1.0, "mist is another switch"


async def test_m42_drives_the_switch_whose_pin_matches() -> None:
    config = make_config(switch={"light": {"pin": "P7"}, **FAN})
    async with running(config) as app:
        await run_job(app, ["M42 P7 S255"])
        assert sim(app).output("P7") == 1.0
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["M42 P3 S255"])
        assert "nothing is configured for P3" in info.value.message


async def test_switches_go_off_at_once_on_halt_and_refuse_commands_until_unlocked() -> None:
    async with running(make_config(switch=FAN)) as app:
        await run_job(app, ["M106"])
        assert sim(app).output("fan") == 1.0
        app.kernel.alarm(10, "stop")
        assert sim(app).output("fan") == 0.0
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["M106"])
        assert info.value.code == 9


async def test_a_soft_reset_while_idle_stops_the_spindle_and_the_switches() -> None:
    async with running(make_config(spindle=SPINDLE, switch=FAN)) as app:
        machine = app.kernel.machine
        await run_job(app, ["M3 S1000", "M106"])
        assert (sim(app).output("spindle"), sim(app).output("fan")) == (1.0, 1.0)
        machine.soft_reset()  # Ctrl-X: no motion, so no alarm and no halt event
        await app.clock.sleep(0.02)  # type: ignore[attr-defined]
        assert (sim(app).output("spindle"), sim(app).output("fan")) == (0.0, 0.0)


@pytest.mark.parametrize(("sections", "expected"), [
    ({"switch": {"fan": {"on_mcode": 3}}},
     "[switch.fan]: on_mcode: M3 belongs to the G-code interpreter"),
    ({"switch": {"fan": {"on_mcode": 106, "off_mcode": 9}}},
     "[switch.fan]: off_mcode = 9 needs on_mcode = 7 (mist) or 8 (flood)"),
    ({"switch": {"fan": {"pin": "a b"}}}, "[switch.fan] pin: String should match pattern"),
    ({"switch": {"fan": {"max_s": -1}}}, "[switch.fan] max_s: Input should be greater than 0"),
    ({"switch": {}}, "[switch]: name each instance, as [switch.NAME]"),
    ({"spindle": {"min_rpm": 2000, "max_rpm": 1000}},
     "[spindle]: min_rpm must be less than max_rpm"),
    ({"spindle": {"spin_up": 1}}, "[spindle] spin_up: unknown key"),
])
def test_bad_switch_and_spindle_configs_name_section_and_key(sections: dict[str, Any],
                                                             expected: str) -> None:
    with pytest.raises(ConfigError) as info:
        make_config(**sections)
    assert f"test.toml: {expected}" in [p[: len(expected) + 11] for p in info.value.problems], \
        info.value.problems
