"""Grbl 1.1's reset, hold and soft-limit semantics on motiond's own machine (the simulated
backend speaks Grbl too), as the grbl-sim rig shows them (tests/e2e/test_grbl_rig.py checks
the same against real Grbl through the Grbl backend)."""

from __future__ import annotations

from server.errors import CommandError, SoftLimitError
from server.kernel.status import snapshot, state_text
from server.protocol.events import Realtime
from server.protocol.lines import LineProtocol
from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running, submit_all


async def test_a_reset_after_a_finished_hold_is_no_alarm_and_in_motion_it_is_alarm_3() -> None:
    async with running(make_config()) as app:
        machine, control = app.kernel.machine, app.kernel.control
        await submit_all(app, ["G1 X100 F3000"])
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        control.hold()
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert state_text(app.kernel) == "Hold:0"
        control.reset()
        assert app.kernel.state is MachineState.IDLE and app.kernel.alarm_code == 0
        assert await submit_all(app, ["G1 X0 F3000"]) == [[]], "no error:9 after the Stop"
        await app.clock.sleep(0.3)  # type: ignore[attr-defined]
        control.reset()  # moving: Grbl alarms, position may be lost
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 3
        del machine


async def test_ctrl_x_resets_the_overrides_and_turns_the_tool_off_in_reports() -> None:
    async with running(make_config()) as app:
        control = app.kernel.control
        await submit_all(app, ["M3 S80", "G1 X1 F600"])
        await app.kernel.machine.wait_idle()
        control.realtime(Realtime.FEED_PLUS_10)
        before = snapshot(app.kernel, 128)
        assert before.overrides[0] == 110 and "S" in before.accessories
        control.reset()
        after = snapshot(app.kernel, 128)
        assert after.overrides == (100, 100, 100)
        assert after.accessories == "" and after.spindle_s == 0


async def test_feed_hold_while_idle_is_hold_0_and_queued_motion_waits_for_resume() -> None:
    async with running(make_config()) as app:
        machine, control = app.kernel.machine, app.kernel.control
        control.hold()
        assert state_text(app.kernel) == "Hold:0"
        await submit_all(app, ["G1 X5 F3000"])
        await app.clock.sleep(0.5)  # type: ignore[attr-defined]
        assert machine.stepgen.state.position_mm[0] == 0.0, "held"
        control.resume()
        await machine.wait_idle()
        assert machine.stepgen.state.position_mm[0] == 5.0
        assert app.kernel.state is MachineState.IDLE
        control.hold()
        control.resume()
        assert app.kernel.state is MachineState.IDLE


def test_a_soft_limit_line_is_answered_by_its_alarm_alone_as_grbl_does() -> None:
    protocol = LineProtocol()
    assert protocol.reply_error(SoftLimitError("X400 beyond the travel")) == b""
    assert protocol.reply_error(CommandError(20)) == b"error:20\r\n"
