"""Findings of a security review, each reproduced against a live server: numbers that are not
finite or not in range are refused where they enter (settings, G-code words, dwell, arcs, JSON
parameters, job files), every entry path applies the line-length limit, the settings file
survives a SIGKILL during a write, and read-only calls on huge files do bounded work off the
event loop."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import random
import signal
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from server.api.server import API_KEY
from server.app import App
from server.config_loader import load_config
from server.errors import CommandError
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.conftest import REPO, make_config
from tests.support.api_client import RpcClient, api_config, client, http_of, serving
from tests.support.helpers import running, submit_all

STALL_BOUND_S = 0.25  # generous on a shared two-core machine; the faults stalled for seconds
HUGE = "1" + "0" * 400  # float() makes it infinity


# -- 1. the settings file survives a crash during a write ---------------------------------------
WRITER = """
import sys
from pathlib import Path
from server.config_loader import build_config
from server.machine.settings import Settings

axis = {"steps_per_mm": 80, "max_rate_mm_s": 500, "accel_mm_s2": 3000, "max_mm": 400}
core = build_config({"axes": {"x": dict(axis), "y": dict(axis)}}).core
settings = Settings(core, Path(sys.argv[1]), is_idle=lambda: True, apply=lambda: None)
value = 1
settings.write("120=2999")  # saved from here on: changed from the config's 3000
settings.write(f"110={value}")
settings.save(settings.file_text())  # the file exists from here on
print("writing", flush=True)
while True:
    value = value % 50_000 + 1
    settings.write(f"110={value}")
    settings.save(settings.file_text())
"""


def test_a_sigkill_during_settings_writes_always_leaves_a_complete_file(tmp_path: Path) -> None:
    path = tmp_path / "machine.settings.toml"
    rng = random.Random(7)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for _ in range(12):
        writer = subprocess.Popen(
            [sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, env=env, cwd=REPO
        )
        assert writer.stdout is not None and writer.stdout.readline() == b"writing\n"
        try:
            writer.wait(rng.uniform(0.005, 0.06))
        except subprocess.TimeoutExpired:
            writer.send_signal(signal.SIGKILL)
        assert writer.wait(10) == -signal.SIGKILL
        saved = tomllib.loads(path.read_text())["settings"]
        assert 1 <= saved["110"] <= 50_000 and saved["120"] == 2999.0


def settings_config(tmp_path: Path) -> Path:
    config_file = tmp_path / "machine.toml"
    config_file.write_text((REPO / "examples" / "plotter.toml").read_text())
    return config_file


@pytest.mark.parametrize(
    "content, why",
    [
        ("", "no [settings] values"),
        ('[settings]\n"120" = ', "not valid TOML"),
        ("# Written by motiond\n", "no [settings] values"),
    ],
)
async def test_an_unreadable_settings_file_is_reported_not_silently_ignored(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, content: str, why: str
) -> None:
    config_file = settings_config(tmp_path)
    saved = tmp_path / "machine.settings.toml"
    saved.write_text(content)
    with caplog.at_level(logging.WARNING, logger="motiond.settings"):
        async with running(load_config(config_file)):
            pass
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(str(saved) in text and why in text for text in warnings), warnings


async def test_a_bad_saved_value_is_reported_and_the_others_still_apply(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config_file = settings_config(tmp_path)
    saved = tmp_path / "machine.settings.toml"
    saved.write_text('[settings]\n"110" = nan\n"130" = inf\n"120" = 900.0\n')
    with caplog.at_level(logging.WARNING, logger="motiond.settings"):
        async with running(load_config(config_file)) as app:
            axis = app.kernel.config.core.axes["x"]
            assert axis.accel_mm_s2 == 900.0
            assert (axis.max_rate_mm_s, axis.max_mm - axis.min_mm) == (150.0, 420.0)
    warnings = " ".join(r.getMessage() for r in caplog.records)
    assert "$110 = nan" in warnings and "$130 = inf" in warnings and str(saved) in warnings


# -- 2. numbers: finite and in range where they enter ---------------------------------------------
@pytest.mark.parametrize(
    "line, code",
    [
        ("$110=inf", 2),
        ("$130=nan", 2),
        ("$10=nan", 2),
        ("$110=" + HUGE, 2),
        ("$120=1e3", 2),
        ("$10=-1", 4),
        ("$11=-0.5", 4),
        ("$110=" + "1" + "0" * 30, 3),
        ("$12=0.000000001", 3),
        ("$12=0", 3),
    ],
)
async def test_settings_refuse_bad_numbers_with_grbl_codes_and_keep_working(
    line: str, code: int
) -> None:
    async with running(make_config()) as app:
        before = await submit_all(app, ["$$"])
        with pytest.raises(CommandError) as info:
            await submit_all(app, [line])
        assert info.value.code == code
        assert await submit_all(app, ["$$"]) == before
        await submit_all(app, ["G1 X10 F6000", "$G"])
        await app.kernel.machine.wait_idle()
        assert app.kernel.state is MachineState.IDLE
        assert app.kernel.machine.stepgen.state.position_mm[0] == 10.0


async def test_rst_is_refused_while_moving_like_a_steps_per_mm_change() -> None:
    async with running(make_config()) as app:
        await submit_all(app, ["$100=100", "G1 X300 F600"])
        for line in ("$RST=$", "$RST=*"):
            with pytest.raises(CommandError) as info:
                await submit_all(app, [line])
            assert info.value.code == 8
        assert app.kernel.config.core.axes["x"].steps_per_mm == 100.0
        await app.kernel.machine.wait_idle()
        await submit_all(app, ["$RST=$"])
        assert app.kernel.config.core.axes["x"].steps_per_mm == 80.0


async def tcp_replies(app: App, lines: list[str]) -> list[str]:
    """Each line's reply over a real socket (one line at a time, as send-response senders do)."""
    port = next(t for t in app.transports if isinstance(t, TcpTransport)).port
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await reader.readuntil(b"]\r\n")  # the banner
    replies = []
    for line in lines:
        writer.write(line.encode() + b"\n")
        reply = ""
        while reply != "ok" and not reply.startswith("error:"):  # skip pushed messages
            reply = (await asyncio.wait_for(reader.readline(), 10)).decode().strip()
        replies.append(reply)
    writer.close()
    return replies


async def test_non_finite_and_huge_words_are_refused_over_tcp_and_nothing_breaks() -> None:
    config = make_config(machine={"soft_limits": False}, protocol={"line_limit": 1024})
    async with running(config, transports=[TcpTransport]) as app:
        replies = await tcp_replies(
            app,
            [
                f"G1 X1 F{HUGE}",  # the parser's fast path
                f"G1 X1 F{HUGE} (a comment sends it down the general path)",
                "G1 X2000000000 F100",
                "G1 Xinf F100",
                "G1 Xnan F100",
                "G1 X1e400 F100",  # X1 and an E word, which Grbl does not have
                f"G4 P{HUGE}",
                "G4 P3601",
                f"G2 X10 R1{'0' * 200}",
                "G2 X10 Y0 R100000000 F100",  # so flat that it would turn into a full circle
                "$12=0.0001",
                "G2 I5000 F100",  # 15,708 chords at that tolerance
                "G4 P0.01",
                "G1 X5 F600",
            ],
        )
        assert replies == ["error:2"] * 5 + ["error:20", "error:2", "error:2"] + [
            "error:2", "error:33", "ok", "error:33", "ok", "ok"]
        await app.kernel.machine.wait_idle()
        (modal,) = await submit_all(app, ["$G"])
        assert modal[0].endswith("F600 S0]") and app.kernel.state is MachineState.IDLE
        assert app.kernel.machine.stepgen.state.position_mm[0] == 5.0


async def test_the_api_refuses_non_finite_params_and_applies_the_line_limit(tmp_path: Path) -> None:
    config = api_config(tmp_path, protocol={"line_limit": 1024}, laser={"pin": "laser"})
    async with serving(config) as (app, address), client(address) as rpc:
        sent = await rpc.call(
            "gcode.send", lines=[f"G1 X1 F{HUGE}", "G1 X1 ;" + "x" * 1100, "$G"],
            stop_on_error=False,
        )
        for method, params in (
            ("settings.set", '{"number": 110, "value": NaN}'),
            ("settings.set", '{"number": 110, "value": 1e400}'),
            ("machine.jog", '{"x": Infinity, "feed_mm_min": 600}'),
            ("laser.fire", '{"percent": 10, "duration_s": Infinity}'),
        ):
            await rpc.connection.send(
                f'{{"jsonrpc": "2.0", "id": "{method}", "method": "{method}", "params": {params}}}'
            )
        # Non-finite numbers are not JSON: refused as the frame is decoded (-32700, id null).
        refused = await parse_errors(rpc, 4)
        assert all(reply["error"]["code"] == -32700 for reply in refused), refused
        precise = await rpc.call("settings.set", number=120, value=1234.56789)
    assert [r["reply"] for r in sent["results"]] == ["error:2", "error:11", "ok"]
    assert sent["results"][2]["messages"][0].endswith("F0 S0]")
    assert precise["value"] == 1234.56789


async def parse_errors(rpc: RpcClient, count: int, timeout_s: float = 10) -> list[dict[str, Any]]:
    """The first ``count`` error replies without an id (frames refused before any method)."""
    async with asyncio.timeout(timeout_s):
        while True:
            found = [m for m in rpc.notifications if m.get("id", "") is None and "error" in m]
            if len(found) >= count:
                return found
            rpc.arrived.clear()
            await rpc.arrived.wait()


async def reply_to(rpc: RpcClient, request_id: str, timeout_s: float = 10) -> dict[str, Any]:
    """The response with this (string) id: the client keeps such replies with notifications."""
    async with asyncio.timeout(timeout_s):
        while True:
            for message in rpc.notifications:
                if message.get("id") == request_id:
                    return message
            rpc.arrived.clear()
            await rpc.arrived.wait()


async def slow_call(rpc: RpcClient, method: str, **params: Any) -> Any:
    """A call that may take longer than the client's usual 10 s on a loaded machine."""
    await rpc.connection.send(
        json.dumps({"jsonrpc": "2.0", "id": method, "method": method, "params": params})
    )
    reply = await reply_to(rpc, method, timeout_s=120)
    assert "error" not in reply, reply
    return reply["result"]


# -- 3. read-only calls on huge files: bounded output, off the loop -----------------------------
def write_raster(path: Path, lines: int) -> None:
    """A back-and-forth raster: 1 mm lines, 0.002 mm apart (200 mm tall for 200k lines)."""
    out = ["G21 G90 M4 S500", "G1 F6000"]
    for i in range(lines // 2):
        out += [f"G1 X{(i + 1) % 2}", f"G1 Y{(i + 1) * 0.002:.3f}"]
    path.write_text("\n".join(out) + "\n")


def estimated(app: App) -> bool:
    progress = app.kernel.jobs.progress()
    return progress is not None and progress.estimate_s is not None


async def test_a_200k_line_raster_toolpath_is_capped_and_no_call_stalls_the_loop(
    tmp_path: Path,
) -> None:
    write_raster(jobs_folder(tmp_path) / "raster.nc", 200_000)
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        monitor = app.kernel.loop_monitor
        monitor.reset()
        path = await slow_call(rpc, "job.toolpath", name="raster.nc", max_segments=5000)
        toolpath_stall_s = monitor.worst_stall_s
        await rpc.call("job.start", name="raster.nc")
        monitor.reset()
        async with asyncio.timeout(120):
            while not estimated(app):  # noqa: ASYNC110 - no event marks the estimate
                await asyncio.sleep(0.01)
        progress = app.kernel.jobs.progress()
        estimate_stall_s = monitor.worst_stall_s
        await rpc.call("job.abort")
    assert path["error"] is None and path["lines"] == 200_002
    assert 0 < path["segments"] <= 5000 and len(path["points"]) == 2 * (path["segments"] + 1)
    assert path["bounds"]["max"] == pytest.approx([1.0, 200.0], abs=path["tolerance_mm"])
    assert path["end"][:2] == [0.0, 200.0]
    assert progress is not None and progress.estimate_s is not None
    assert progress.estimate_s > 100 and progress.lines_total == 200_002
    assert toolpath_stall_s < STALL_BOUND_S and estimate_stall_s < STALL_BOUND_S


async def test_the_toolpath_cache_keeps_only_the_latest_results(tmp_path: Path) -> None:
    write_raster(jobs_folder(tmp_path) / "small.nc", 2000)
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        for cap in (100, 200, 300, 200):
            path = await rpc.call("job.toolpath", name="small.nc", max_segments=cap)
            assert path["segments"] <= cap
        cached = http_of(app).app[API_KEY].methods.toolpaths
    assert [key[-1] for key in cached] == [300, 200]


async def test_a_job_with_a_2_mb_line_stops_there_with_error_11_without_stalling(
    tmp_path: Path,
) -> None:
    long_line = "G1 X1" * 400_000
    (jobs_folder(tmp_path) / "long.nc").write_text(f"G21 G90\nG1 X5 F3000\n{long_line}\nG0 X9\n")
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        monitor = app.kernel.loop_monitor
        monitor.reset()
        await rpc.call("job.start", name="long.nc")
        await asyncio.wait_for(app.kernel.jobs._task, 60)  # noqa: SLF001 - the player task
        progress = app.kernel.jobs.progress()
        path = await slow_call(rpc, "job.toolpath", name="long.nc")
        stall_s = monitor.worst_stall_s
        await app.kernel.machine.wait_idle()
        position = app.kernel.machine.stepgen.state.position_mm
    assert progress is not None and progress.state == "failed" and progress.error is not None
    assert progress.error.startswith("line 3: error:11 line longer than 256 bytes")
    assert position[0] == 5.0, "the lines before it ran, none after"
    assert path["error_line"] == 3 and path["error"].startswith("error:11")
    assert stall_s < STALL_BOUND_S


def jobs_folder(data_dir: Path) -> Path:
    """The job files' folder of a server whose data folder is ``data_dir``."""
    folder = data_dir / "jobs"
    folder.mkdir(parents=True, exist_ok=True)
    return folder
