"""Probing against the simulated machine, and the simulated machine's trace file."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from server.runtime.events import MachineState
from tests.conftest import make_config
from tests.support.helpers import running, submit_all


async def test_g38_2_stops_at_the_probe_and_reports_the_contact_position() -> None:
    config = make_config(backend={"probe_at_mm": {"z": -5.0}})
    async with running(config) as app:
        (reply,) = await submit_all(app, ["G38.2 Z-20 F120"])
        assert len(reply) == 1 and reply[0].startswith("[PRB:0.000,0.000,-5.0") and \
            reply[0].endswith(":1]")
        machine = app.kernel.machine
        z = machine.stepgen.state.position_mm[2]
        assert z == pytest.approx(-5.0, abs=0.01)
        assert machine.interpreter.position[2] == pytest.approx(z)
        assert machine.backend.steps[2] == round(z * 400)
        assert await submit_all(app, ["G91 G0 Z2", "G90"]) == [[], []]
        await machine.wait_idle()
        assert machine.stepgen.state.position_mm[2] == pytest.approx(z + 2)
        assert "[PRB:0.000,0.000,-5.0" in (await submit_all(app, ["$#"]))[0][-1]


async def test_a_probe_that_never_touches_raises_alarm_5_but_g38_3_does_not() -> None:
    async with running(make_config()) as app:
        (reply,) = await submit_all(app, ["G38.3 Z-3 F300"])
        assert reply == ["[PRB:0.000,0.000,-3.000:0]"]
        assert app.kernel.state is not MachineState.ALARM
        await submit_all(app, ["G38.2 Z-6 F300"])
        assert app.kernel.state is MachineState.ALARM and app.kernel.alarm_code == 5


async def test_the_sim_backend_writes_a_trace_file_of_the_whole_run(tmp_path: Path) -> None:
    trace = tmp_path / "trace.csv"
    async with running(make_config(backend={"trace_csv": str(trace)})) as app:
        await submit_all(app, ["G1 X10 F600"])
        await app.kernel.machine.wait_idle()
    rows = list(csv.reader(trace.open()))
    assert rows[0] == ["time_s", "x_mm", "y_mm", "z_mm", "speed_mm_s", "power"]
    assert float(rows[-1][1]) == pytest.approx(10.0)
    speeds = [float(row[4]) for row in rows[1:]]
    assert max(speeds) == pytest.approx(10.0, rel=1e-6)
