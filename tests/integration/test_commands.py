"""Grbl's $ commands through the dispatcher: settings live and persisted, $N, $RST, $SLP, $C."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.config_loader import load_config
from server.errors import CommandError
from server.runtime.events import MachineState
from tests.conftest import REPO, make_config
from tests.support.helpers import running, submit_all


def settings_of(reply: list[str]) -> dict[int, str]:
    return {int(line[1:].split("=")[0]): line.split("=")[1] for line in reply}


async def test_settings_read_in_grbl_format_and_apply_live() -> None:
    async with running(make_config()) as app:
        (listing,) = await submit_all(app, ["$$"])
        values = settings_of(listing)
        assert values[10] == "1" and values[20] == "1" and values[100] == "80.000"
        assert values[110] == "30000.000" and values[11] == "0.010"
        await submit_all(app, ["$110=6000", "$11=0.05"])
        planner = app.kernel.machine.planner
        assert planner.settings.max_rate_mm_s[0] == pytest.approx(100.0)
        assert planner.settings.junction_deviation_mm == pytest.approx(0.05)
        start = app.clock.now_s()
        await submit_all(app, ["G0 X200"])
        await app.kernel.machine.wait_idle()
        assert app.clock.now_s() - start >= 2.0, "the rapid now runs at 6000 mm/min"


@pytest.mark.parametrize("line, code", [("$999=1", 3), ("$110=-5", 4), ("$0=3", 5),
                                        ("$110=abc", 2), ("$N5=G0", 3)])
async def test_bad_settings_are_refused_with_grbl_codes_and_change_nothing(
    line: str, code: int
) -> None:
    async with running(make_config()) as app:
        before = await submit_all(app, ["$$"])
        with pytest.raises(CommandError) as info:
            await submit_all(app, [line])
        assert info.value.code == code
        assert await submit_all(app, ["$$"]) == before


async def test_geometry_settings_wait_for_an_idle_machine() -> None:
    async with running(make_config()) as app:
        await submit_all(app, ["G1 X300 F600"])
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["$100=100"])
        assert info.value.code == 8


async def test_settings_persist_next_to_the_config_and_restore_with_rst(tmp_path: Path) -> None:
    config_file = tmp_path / "machine.toml"
    config_file.write_text((REPO / "examples" / "plotter.toml").read_text())
    async with running(load_config(config_file)) as app:
        await submit_all(app, ["$120=900", "$13=1"])
    saved = tmp_path / "machine.settings.toml"
    assert '"120" = 900.0' in saved.read_text()
    async with running(load_config(config_file)) as app:
        values = settings_of((await submit_all(app, ["$$"]))[0])
        assert (values[120], values[13]) == ("900.000", "1")
        await submit_all(app, ["$RST=$"])
        values = settings_of((await submit_all(app, ["$$"]))[0])
        assert (values[120], values[13]) == ("1500.000", "0")
    assert not saved.exists()


async def test_startup_lines_sleep_and_check_mode() -> None:
    async with running(make_config()) as app:
        assert await submit_all(app, ["$N0=G21 G90", "$N"]) == [[], ["$N0=G21 G90", "$N1="]]
        with pytest.raises(CommandError):
            await submit_all(app, ["$N1=G1 X"])
        assert await submit_all(app, ["$C", "G0 X50", "$G"]) == [
            ["[MSG:Enabled]"], [], ["[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"]]
        assert app.kernel.state is MachineState.CHECK
        assert len(app.kernel.machine.planner) == 0, "check mode moves nothing"
        assert await submit_all(app, ["$C"]) == [["[MSG:Disabled]"]]
        assert app.kernel.machine.interpreter.position == (0.0, 0.0, 0.0)
        assert await submit_all(app, ["$SLP"]) == [[]]
        assert app.kernel.state is MachineState.SLEEP


async def test_help_build_info_and_version() -> None:
    async with running(make_config()) as app:
        help_, info, version = await submit_all(app, ["$", "$I", "version"])
        assert help_[0].startswith("[HLP:$$ $# $G $I $N")
        assert info[0].startswith("[VER:1.1h.motiond") and info[1] == "[OPT:VL,15,128]"
        assert version[0].startswith("Build version: motiond-")


async def test_the_status_shows_s_only_while_the_spindle_or_laser_is_on() -> None:
    from server.kernel.status import snapshot

    async with running(make_config()) as app:
        await submit_all(app, ["M4 S500", "G1 X5 F3000"])
        await app.kernel.machine.wait_idle()
        assert snapshot(app.kernel, 128).spindle_s == 500
        await submit_all(app, ["M5", "G1 X6"])
        await app.kernel.machine.wait_idle()
        assert snapshot(app.kernel, 128).spindle_s == 0
