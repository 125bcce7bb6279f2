"""Stop means stop, on every path (issue #36), over TCP and the JSON API.

A laser machine is served in this process on real ports (:mod:`tests.support.stop_rig`),
on the real clock; Grbl senders and RepRap hosts speak to it over real TCP connections, the
operator's JSON client over a real WebSocket. Each test makes a stop come from one path while
something was asked for on another (a job's start being checked, another sender's queued
lines, the modal laser state, lines behind a Ctrl-X in the same write, a frame), and checks
what the machine did, from the simulated backend's steps and laser output: nothing asked for
before a stop runs after it, the laser stays off, and every request gets the answer a sender
expects (an error, the banner, or nothing for lines a reset dropped).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from functools import reduce
from operator import xor
from pathlib import Path

import pytest

from tests.support.api_client import RpcClient, client
from tests.support.stop_rig import (
    BANNER,
    STOP_AFTER_S,
    LineClient,
    Rig,
    assert_a_reset_boards_modes,
    field_of,
    slow_to_check_job,
    stop_rig,
)


def frame(number: int, text: str) -> bytes:
    """A RepRap line: ``N<number> <text>*<checksum>``."""
    head = f"N{number} {text}"
    return f"{head}*{reduce(xor, head.encode(), 0)}\n".encode()


async def wait_api_state(rpc: RpcClient, state: str, polls: int = 250) -> None:
    """Poll ``machine.status`` every 20 ms until its state is ``state``."""
    for _ in range(polls):
        if (await rpc.call("machine.status"))["state"] == state:
            return
        await asyncio.sleep(0.02)
    raise AssertionError(f"the machine never reached {state}")


# -- 1. a job whose start is still being checked -------------------------------------------------
async def _ctrl_x(operator: LineClient, rpc: RpcClient) -> None:
    operator.send(b"\x18")
    await operator.until(lambda got: got.count(BANNER) == 2)


async def _m112_then_unlock(operator: LineClient, rpc: RpcClient) -> None:
    assert await operator.command("M112") == [
        "ALARM:40", "[MSG:emergency stop (M112): $X or M999 to unlock]", "ok"]
    assert (await operator.command("$X"))[-1] == "ok"


async def _machine_reset(operator: LineClient, rpc: RpcClient) -> None:
    await rpc.call("machine.reset")


START_STOPS: dict[str, Callable[[LineClient, RpcClient], Awaitable[None]]] = {
    "ctrl-x": _ctrl_x, "m112-then-unlock": _m112_then_unlock, "machine.reset": _machine_reset}


@pytest.mark.parametrize("stop", list(START_STOPS))
async def test_a_job_whose_start_is_being_checked_never_starts_after_a_stop(
        tmp_path: Path, stop: str) -> None:
    async with stop_rig(tmp_path) as rig, client(rig.http) as starter, \
            client(rig.http) as watcher:
        rig.write_job("big.nc", slow_to_check_job())
        operator = await rig.tcp()
        start = asyncio.create_task(starter.request("job.start", name="big.nc"))
        await asyncio.sleep(STOP_AFTER_S)
        assert not start.done(), f"the check ended before the stop: {start.result()}"
        await START_STOPS[stop](operator, watcher)
        answer = await asyncio.wait_for(start, 10)
        assert "error" in answer and answer["error"]["code"] == 45, answer
        await rig.assert_still(1.5, "after the stop")  # the job's first moves: 0.1 s in
        status = await watcher.call("machine.status")
    assert status["state"] == "Idle" and status["job"] is None, status
    assert status["power_pct"] == 0.0 and status["tool"]["mode"] == "M5"


# -- 2. another connection's stream -------------------------------------------------------------
async def _hold_and_reset_on_tcp(rig: Rig, rpc: RpcClient | None = None) -> None:
    operator = await rig.tcp()
    operator.send(b"!")
    await operator.wait_state("Hold:0")
    operator.send(b"\x18")
    await operator.until(lambda got: got.count(BANNER) == 2)


async def _hold_and_reset_on_the_api(rig: Rig, rpc: RpcClient) -> None:
    await rpc.call("machine.hold")
    await wait_api_state(rpc, "Hold:0")
    await rpc.call("machine.reset")


@pytest.mark.parametrize("operator", [_hold_and_reset_on_tcp, _hold_and_reset_on_the_api],
                         ids=["tcp", "json-api"])
async def test_a_hold_and_reset_drop_what_another_sender_queued_with_its_banner_and_no_ok(
        tmp_path: Path, operator: Callable[[Rig, RpcClient], Awaitable[None]]) -> None:
    moves = 100  # 10 s of cutting; the planner takes 0.5 s of it, the rest waits in B's queue
    async with stop_rig(tmp_path) as rig, client(rig.http) as rpc:
        sender = await rig.tcp()
        sender.send(b"G21 G90\n" + b"".join(
            f"G1 X{1 + i} F600 M3 S1000\n".encode() for i in range(moves)))
        await sender.until(lambda got: got.count("ok") >= 4)
        await rig.moving()
        assert rig.laser_fired_since(0), "the sender's lines cut"
        await operator(rig, rpc)
        await rig.assert_still(1.2, "after the reset")  # 8.5 s of B's moves were waiting
        assert sender.lines.count(BANNER) == 2, "B is told to count from nothing again"
        assert sender.lines[-1] == BANNER, "no ok for the dropped lines"
        acknowledged = sender.lines.count("ok")
        assert acknowledged < moves // 2
        assert await sender.command("G4 P0") == ["ok"], "B's next line is its own"
        await sender.wait_state("Idle")
        status = await rpc.call("machine.status")
    assert status["state"] == "Idle" and status["power_pct"] == 0.0, status


async def test_a_hold_and_reset_refuse_each_line_a_reprap_host_queued_and_run_none(
        tmp_path: Path) -> None:
    """A RepRap host waits for one reply per line (no banner tells it to start again): each
    line the reset overtook is refused, Marlin's way (``echo:`` then ``ok``), and none runs."""
    moves = 100
    async with stop_rig(tmp_path) as rig:
        host = await rig.tcp()
        assert (await host.command("N0 M110 N0*125"))[-1] == "ok"
        host.send(b"G21 G90\n" + b"".join(
            f"G1 X{1 + i} F600 M3 S1000\n".encode() for i in range(moves)))
        await host.until(lambda got: got.count("ok") >= 5)
        await rig.moving()
        await _hold_and_reset_on_tcp(rig)
        await rig.assert_still(1.2, "after the reset")
        refused = [line for line in host.lines if line.startswith("echo:") and "not run" in line]
    assert host.lines.count("ok") == 1 + 1 + moves, "one reply per line"
    assert len(refused) > moves // 2, host.lines[-4:]
    assert host.lines.count(BANNER) == 1, "no Grbl banner for a RepRap host"


# -- 3. every stop leaves the laser off in the modal state ---------------------------------------
async def _m112(rig: Rig, sender: LineClient, rpc: RpcClient) -> None:
    assert "ALARM:40" in await sender.command("M112")  # (its ok too: then $X's reply)
    assert (await sender.command("$X"))[-1] == "ok"


async def _framed_m112(rig: Rig, sender: LineClient, rpc: RpcClient) -> None:
    host = await rig.tcp()
    assert (await host.command("N0 M110 N0*125"))[-1] == "ok"  # OctoPrint's first line
    host.send(frame(1, "M112"))
    await host.until(lambda got: "ALARM:40" in got)
    host.send(frame(2, "M999"))
    await host.until(lambda got: "[MSG:Caution: Unlocked]" in got)


async def _api_estop(rig: Rig, sender: LineClient, rpc: RpcClient) -> None:
    await rpc.call("machine.estop")
    await rpc.call("machine.unlock")


async def _soft_limit(rig: Rig, sender: LineClient, rpc: RpcClient) -> None:
    sender.send(b"G1 X1000\n")  # beyond the 400 mm of travel
    await sender.until(lambda got: "ALARM:2" in got)
    assert (await sender.command("$X"))[-1] == "ok"


async def _reset(rig: Rig, sender: LineClient, rpc: RpcClient) -> None:
    sender.send(b"\x18")
    await sender.until(lambda got: "ALARM:3" in got and got.count(BANNER) == 2)
    assert (await sender.command("$X"))[-1] == "ok"


MODAL_STOPS = {"m112": _m112, "framed-m112-then-m999": _framed_m112, "api-estop": _api_estop,
               "soft-limit-alarm": _soft_limit, "ctrl-x": _reset}


@pytest.mark.parametrize("stop", list(MODAL_STOPS))
async def test_after_a_stop_and_unlock_the_modal_state_is_m5_s0_m9_and_the_next_move_is_dark(
        tmp_path: Path, stop: str) -> None:
    async with stop_rig(tmp_path) as rig, client(rig.http) as rpc:
        sender = await rig.tcp()
        assert await sender.command("G10 L20 P1 X-5 Y-3") == ["ok"]
        assert await sender.command("M3 S800") == ["ok"]
        assert await sender.command("G1 X30 F600") == ["ok"]
        await rig.moving()
        assert rig.laser_fired_since(0), "the move cut"
        await MODAL_STOPS[stop](rig, sender, rpc)
        await assert_a_reset_boards_modes(rig, sender)


# -- 5. MeerK40t's Stop ------------------------------------------------------------------------
async def test_a_ctrl_x_flushes_the_lines_written_right_behind_it_as_meerk40t_stops(
        tmp_path: Path) -> None:
    async with stop_rig(tmp_path) as rig:
        sender = await rig.tcp()
        assert await sender.command("M3 S300 G1 X30 F600") == ["ok"]
        await rig.moving()
        mark = len(sender.lines)
        sender.send(b"\x18G1 S0\nM5\n")  # MeerK40t's Stop: one write
        await sender.until(lambda got: BANNER in got[mark:])
        await rig.assert_still(1.0, "after the reset")  # (an answer to the lines meanwhile)
    assert [line for line in sender.lines[mark:] if line] == [
        "ALARM:3", BANNER, "[MSG:'$H'|'$X' to unlock]",
        "[MSG:reset while in motion: position may be lost, re-home]"]  # Grbl's, then ours


@pytest.mark.parametrize("comment", ["(outer contour, first pass)", "(激光切割外轮廓第一层)"],
                         ids=["ascii-comment", "utf-8-comment"])
async def test_every_byte_written_right_behind_a_ctrl_x_is_flushed_whatever_it_holds(
        tmp_path: Path, comment: str) -> None:
    """What follows a Ctrl-X in the same write is dropped, as Grbl's reset flushes its
    buffer: also when the write holds more than one slice of realtime-looking bytes (30
    bytes of UTF-8 in a CAM comment), not only up to the end of the Ctrl-X's slice."""
    async with stop_rig(tmp_path) as rig:
        sender = await rig.tcp()
        mark = len(sender.lines)
        sender.send(b"\x18" + f"G4 P0 {comment}\nG1 X5 F600\n".encode())
        await sender.until(lambda got: BANNER in got[mark:])
        await rig.assert_still(1.0, "after the reset")
    assert [line for line in sender.lines[mark:] if line] == [BANNER]


# -- 6. M112 acts whatever its framing says ------------------------------------------------------
@pytest.mark.parametrize("line", [b"N1 M112*99\n", frame(77, "M112")],  # (N1 M112*32)
                         ids=["wrong-checksum", "out-of-sequence"])
async def test_a_refused_reprap_frame_holding_m112_still_halts_at_once(
        tmp_path: Path, line: bytes) -> None:
    async with stop_rig(tmp_path) as rig:
        operator = await rig.tcp()
        host = await rig.tcp()
        assert (await host.command("N0 M110 N0*125"))[-1] == "ok"
        host.send(b"G1 X30 F600\n")
        await rig.moving()
        host.send(line)
        await host.until(lambda got: "ALARM:40" in got, timeout_s=1.0)
        await rig.assert_still(1.0, "after the M112")
        report = await operator.report()
    assert report.startswith("<Alarm|"), report
    assert "Resend: 1" in host.lines, "the frame itself is refused, as before"


# -- 7. a hold in laser mode reports the laser off -----------------------------------------------
async def test_a_held_laser_reports_no_power_and_no_spindle_state(tmp_path: Path) -> None:
    async with stop_rig(tmp_path) as rig:
        sender = await rig.tcp()
        assert await sender.command("M4 S500 G1 X30 F600") == ["ok"]
        await rig.moving()
        assert field_of(await sender.report(), "FS") == "600,500", "it cuts before the hold"
        sender.send(b"!")
        held = await sender.wait_state("Hold:0")
        reports = [await sender.report() for _ in range(30)]  # Ov (and A) come every 10-20
        assert rig.laser_duty() == 0.0
    assert field_of(held, "FS") == "0,0", held
    with_overrides = [report for report in reports if field_of(report, "Ov") is not None]
    assert with_overrides, reports
    assert all(field_of(report, "A") is None for report in [held, *reports]), reports


# -- 8. a hold during a powered frame ------------------------------------------------------------
async def test_a_hold_during_a_powered_frame_answers_the_call_soon_with_stopped_and_why(
        tmp_path: Path) -> None:
    async with stop_rig(tmp_path, jobs={"frame_feed_mm_min": 600, "frame_power_s": 10}) as rig, \
            client(rig.http) as framer, client(rig.http) as operator:
        rig.write_job("box.nc", "G21 G90\nG1 X40 Y20 F600\nG1 X0 Y0\n")  # 12 s round its frame
        frame_call = asyncio.create_task(framer.request("job.frame", name="box.nc"))
        await rig.moving()
        assert rig.laser_fired_since(0), "the frame runs at low power"
        await operator.call("machine.hold")
        answered, _ = await asyncio.wait({frame_call}, timeout=2.0)
        assert answered, "job.frame did not answer within 2 s of the hold"
        await rig.assert_still(1.0, "after the hold")
    answer = frame_call.result()
    assert "result" in answer, answer
    assert answer["result"]["stopped"] is True and answer["result"]["reason"], answer
