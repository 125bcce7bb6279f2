"""Real senders from PyPI driving a running motiond end to end.

* grbl-streamer over the pseudo-terminal: Ctrl-X, ``$$``/``$#``/``$G``, ``?`` polling every
  0.2 s, character counting at 128 bytes, lines rewritten without spaces.
* printrun's ``printcore`` over TCP (``host:port``: RepRap dialect, one ``ok`` per line) and over
  the pseudo-terminal (``N.. *checksum`` framing with ``M110 N-1``).

Each streams a whole corpus job. The server runs in-process; the senders' threads run beside
its event loop. Every line the sender wrote must get exactly one ``ok`` and no refusal, the
planner must receive exactly the moves an independent parse + interpreter run of the file
produces (same order, none lost, none twice), and the steps must end exactly at the file's end.

On the virtual clock the job's motion takes no real time; the real-clock run executes the
same path with feeds scaled up on a fast machine, so the senders' timers meet real motion.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

# Real senders from PyPI: a missing one must fail the run, never skip it. grbl-streamer comes
# with the test extras; Printrun is installed with --no-deps (see scripts/setup-tests),
# since its GUI dependencies (wxPython, dbus) cannot build here and printcore needs neither.
import grbl_streamer  # noqa: E402, F401
import printrun.printcore  # noqa: E402, F401
import pytest

from server.app import App
from server.config import Config
from server.runtime.clock import Clock, RealClock, VirtualClock
from server.runtime.events import MachineState
from server.transports.serial import SerialTransport
from server.transports.tcp import TcpTransport
from tests.conftest import CORPUS, make_config
from tests.support.helpers import running
from tests.support.senders import (
    GrblStreamerRun,
    MoveSpy,
    PrintcoreRun,
    backend_steps,
    expected_run,
    fast_axes,
    job_lines_from,
    scale_feeds,
    wait_for,
)

pytestmark = pytest.mark.usefixtures("quick_thread_switches")


def job_config(clock: str, tmp_path: Path) -> tuple[Config, Clock]:
    """Virtual: the corpus test machine, coarse ticks (fast). Real: a fast machine, 1 kHz."""
    common: dict[str, Any] = {"machine": {"soft_limits": False},
                              "serial": {"pty": str(tmp_path / "ttyMotiond")}}
    if clock == "virtual":
        return make_config(stepgen={"tick_hz": 100.0}, **common), VirtualClock()
    return make_config(axes=fast_axes(), **common), RealClock()


def job(name: str, clock: str) -> list[str]:
    lines = job_lines_from(CORPUS / name)
    return lines if clock == "virtual" else scale_feeds(lines, 40.0)


def assert_exact_end(app: App, lines: list[str], spy: MoveSpy) -> None:
    core = app.kernel.config.core
    expected = expected_run(lines, core)
    assert not expected.errors, "the job itself must be valid on this machine"
    assert len(spy.targets) == len(expected.targets)
    assert spy.targets == expected.targets, "moves lost, repeated or reordered"
    assert backend_steps(app.kernel.machine) == expected.end_steps(core)
    assert app.kernel.machine.stepgen.state.position_mm == pytest.approx(expected.end_mm)


@pytest.mark.parametrize("clock", ["virtual", "real"])
async def test_grbl_streamer_over_the_pty_streams_a_corpus_job_to_the_end(
        clock: str, tmp_path: Path) -> None:
    config, server_clock = job_config(clock, tmp_path)
    lines = job("laser-vector-jsdc.gcode", clock)
    async with running(config, server_clock, [SerialTransport]) as app:
        spy = MoveSpy(app.kernel.machine)
        sender = GrblStreamerRun()
        try:
            await sender.connect(str(tmp_path / "ttyMotiond"))
            assert sender.boots >= 1 and not sender.errors
            await sender.run_job(lines, timeout_s=120.0)
            await asyncio.wait_for(app.kernel.machine.wait_idle(), 60.0)
            expected = expected_run(lines, app.kernel.config.core)
            end = tuple(round(v, 3) for v in expected.end_mm)
            await wait_for(lambda: sender.streamer.cmode == "Idle"
                           and tuple(sender.streamer.cmpos) == end, 5.0,
                           "grbl-streamer's own status poll to show the end, Idle")
        finally:
            await sender.close()
        streamer = sender.streamer
        assert not sender.errors and not sender.alarms
        assert len(sender.sent) == streamer.buffer_size >= len(lines)
        assert sender.processed == len(sender.sent), "a job line was never acknowledged"
        assert sender.oks == len(sender.writes), "one ok per line written, no more, no less"
        assert any(state == "Run" for state, _ in sender.states), "its ? polling saw the motion"
        assert app.kernel.state is MachineState.IDLE
        assert_exact_end(app, lines, spy)
        # what went down the pty (rewritten without spaces) means the same moves
        assert sender.job_wire() == sender.sent
        assert expected_run(sender.sent, app.kernel.config.core).targets == spy.targets


@pytest.mark.parametrize("clock", ["virtual", "real"])
async def test_printcore_over_tcp_streams_a_corpus_job_to_the_end(
        clock: str, tmp_path: Path) -> None:
    config, server_clock = job_config(clock, tmp_path)
    name = "cnc-arcs-arrows.nc" if clock == "virtual" else "laser-vector-jsdc.gcode"
    lines = job(name, clock)
    async with running(config, server_clock, [TcpTransport]) as app:
        spy = MoveSpy(app.kernel.machine)
        sender = PrintcoreRun()
        port = app.transports[0].port  # type: ignore[attr-defined]
        try:
            await sender.connect(f"127.0.0.1:{port}")
            await sender.run_job(lines, timeout_s=180.0)
            await asyncio.wait_for(app.kernel.machine.wait_idle(), 60.0)
        finally:
            await sender.close()
        assert sender.refusals() == [] and sender.host_errors == []
        assert sender.sent[0] == "M105" and "M110 N-1" in sender.sent
        job_lines = [line for line in sender.sent if line not in ("M105", "M110 N-1")]
        assert len(job_lines) == sum(1 for line in lines if _code_of(line))
        assert sender.oks == len(sender.sent), "one ok per line sent"
        assert app.kernel.state is MachineState.IDLE
        assert_exact_end(app, lines, spy)


async def test_printcore_over_the_pty_frames_every_line_with_number_and_checksum(
        tmp_path: Path) -> None:
    config, server_clock = job_config("virtual", tmp_path)
    lines = job("laser-vector-jsdc.gcode", "virtual")
    async with running(config, server_clock, [SerialTransport]) as app:
        spy = MoveSpy(app.kernel.machine)
        sender = PrintcoreRun()
        try:
            await sender.connect(str(tmp_path / "ttyMotiond"))
            await sender.run_job(lines, timeout_s=120.0)
            await asyncio.wait_for(app.kernel.machine.wait_idle(), 60.0)
        finally:
            await sender.close()
        framed = [line for line in sender.sent if line.startswith("N")]
        assert framed[0].startswith("N-1 M110 N-1*")
        assert len(framed) == sum(1 for line in lines if _code_of(line)) + 2
        assert framed[-2].startswith(f"N{len(framed) - 3} ")
        assert sender.refusals() == [] and sender.host_errors == []
        assert sender.oks == len(sender.sent)
        assert_exact_end(app, lines, spy)


def _code_of(line: str) -> str:
    """A line as printcore sends it: comments stripped (empty: not sent)."""
    from printrun import gcoder

    return gcoder.gcode_strip_comment_exp.sub("", line).strip()
