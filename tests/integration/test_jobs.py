"""Job files: stored safely, played through the dispatcher, stopped at the first bad line."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.errors import CommandError
from tests.conftest import CORPUS, make_config
from tests.support.helpers import running, submit_all


def config_in(tmp_path: Path):
    return make_config(jobs={"data_dir": str(tmp_path)})


@pytest.mark.parametrize("name", ["../x.nc", "/etc/passwd", "a/b.nc", ".hidden", "x\0.nc", "",
                                  "..", "a\\b.nc"])
async def test_names_that_escape_the_data_directory_are_refused(tmp_path: Path, name: str) -> None:
    async with running(config_in(tmp_path)) as app:
        with pytest.raises(CommandError) as info:
            await app.kernel.jobs.save(name, b"G0 X1\n")
        assert info.value.code == 44
        assert list(tmp_path.rglob("*.nc")) == list(tmp_path.rglob(".upload-*")) == []


async def test_upload_list_and_play_a_job_to_its_end(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        jobs = app.kernel.jobs
        data = b"G21 G90\nG1 X10 F3000\nG1 Y10\nG1 X0\nG1 Y0\nG1 X3 Y4\n"
        await jobs.save("square.nc", data)
        assert [(f.name, f.size_bytes) for f in jobs.files()] == [("square.nc", len(data))]
        assert await submit_all(app, ["ls -s", "play /sd/square.nc"]) == [
            [f"square.nc {len(data)}"], ["[MSG:Playing square.nc]"]]
        await jobs._task  # noqa: SLF001 - wait for the player to finish
        progress = jobs.progress()
        assert progress is not None
        assert (progress.state, progress.lines_done, progress.percent) == ("done", 6, 100.0)
        assert app.kernel.machine.stepgen.state.position_mm == (3.0, 4.0, 0.0)
        assert app.kernel.machine.backend.steps == [240, 320, 0]


async def test_a_corpus_job_stops_with_a_clear_error_at_the_bad_line(tmp_path: Path) -> None:
    pushed: list[str] = []
    data = (CORPUS / "cnc-helical-thread.gcode").read_bytes()
    async with running(make_config(jobs={"data_dir": str(tmp_path)},
                                   machine={"soft_limits": False})) as app:
        app.kernel.events.subscribe("push", pushed.append)
        await app.kernel.jobs.save("thread.gcode", data)
        app.kernel.jobs.play("thread.gcode")
        await app.kernel.jobs._task  # noqa: SLF001
        progress = app.kernel.jobs.progress()
        assert progress is not None and progress.state == "failed"
        assert progress.error is not None and progress.error.startswith("line 5: error:20")
        assert any("stopped at line 5: error:20" in line for line in pushed)


async def test_only_one_job_plays_at_a_time_and_abort_stops_motion(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        jobs = app.kernel.jobs
        await jobs.save("long.nc", b"G1 X300 F600\nG1 X0\n")
        jobs.play("long.nc")
        with pytest.raises(CommandError) as info:
            jobs.play("long.nc")
        assert info.value.code == 45
        await app.clock.sleep(2.0)  # type: ignore[attr-defined]
        assert app.kernel.machine.stepgen.state.moving
        assert (await submit_all(app, ["abort"]))[0] == ["[MSG:Aborted playing or paused file]"]
        assert not app.kernel.machine.stepgen.state.moving
        x = app.kernel.machine.stepgen.state.position_mm[0]
        assert 0 < x < 300
        assert app.kernel.jobs.progress().state == "aborted"  # type: ignore[union-attr]
        assert await submit_all(app, ["G0 X0"]) == [[]], "the machine is usable after an abort"


async def test_missing_file_and_progress_when_idle(tmp_path: Path) -> None:
    async with running(config_in(tmp_path)) as app:
        with pytest.raises(CommandError) as info:
            await submit_all(app, ["play nothing.nc"])
        assert info.value.code == 44
        assert await submit_all(app, ["progress"]) == [["[MSG:Not currently playing]"]]


async def test_a_full_disk_leaves_no_partial_file(tmp_path: Path) -> None:
    async def failing_chunks():
        yield b"G0 X1\n"
        raise OSError(28, "No space left on device")

    async with running(config_in(tmp_path)) as app:
        with pytest.raises(CommandError) as info:
            await app.kernel.jobs.save_stream("big.nc", failing_chunks(), 1 << 20)
        assert info.value.code == 44 and "No space left on device" in info.value.message
        assert list(tmp_path.rglob("*.nc")) == list(tmp_path.rglob(".upload-*")) == []
