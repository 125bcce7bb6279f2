"""``[mqtt]`` against a real Mosquitto broker, with real ``motiond`` processes.

Availability is retained with a last will, status is retained and follows a running job,
commands are refused unless ``allow_control`` and answered one reply per line, the broker can
restart mid-job without touching motion, and ``motiond fleet`` lists every machine.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

from tests.support.broker import Broker, mosquitto, mqtt_toml, watching
from tests.support.processes import REPO, Served, motiond

PREFIX = "motiond/mill-1"
MACHINE = '[machine]\nname = "Mill 1"\n'


async def tcp_report(port: int) -> str:
    """A ``?`` status report from the server's raw TCP port."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        await asyncio.wait_for(reader.readuntil(b"for help]"), 5)  # the banner
        writer.write(b"?")
        await writer.drain()
        line = await asyncio.wait_for(reader.readuntil(b">"), 5)
        return line.decode()[line.decode().index("<"):]
    finally:
        writer.close()


def mpos(report: str) -> list[float]:
    field = next(part for part in report.strip("<>").split("|") if part.startswith("MPos:"))
    return [float(value) for value in field[5:].split(",")]


def is_online(payload: bytes) -> bool:
    return payload == b"online"


def serve(tmp_path: Path, broker: Broker, **options: Any) -> Any:
    return motiond(tmp_path, MACHINE + mqtt_toml(broker, **options))


async def test_availability_is_retained_and_a_killed_server_shows_offline(
    tmp_path: Path,
) -> None:
    async with (
        mosquitto(tmp_path / "broker") as broker,
        serve(tmp_path, broker, keepalive_s=5) as served,
    ):
        async with watching(broker, f"{PREFIX}/#") as live:
            await live.wait_for(f"{PREFIX}/availability", is_online)
            status = await live.wait_json(f"{PREFIX}/status")
        # a client that arrives later still gets the retained state and the HA configs
        async with watching(broker, f"{PREFIX}/+", "homeassistant/#") as late:
            assert await late.wait_for(f"{PREFIX}/availability") == b"online"
            retained = await late.wait_json(f"{PREFIX}/status")
            state = await late.wait_json("homeassistant/sensor/mill-1/state/config")
            alarm = await late.wait_json("homeassistant/binary_sensor/mill-1/alarm/config")
            served.process.send_signal(signal.SIGKILL)
            await late.wait_for(f"{PREFIX}/availability", lambda p: p == b"offline")
    assert status["machine"] == "Mill 1" and status["state"] == "Idle"
    assert status["alarm"] is None and status["mpos"] == [0.0, 0.0] and status["job"] is None
    assert retained == status
    assert state["state_topic"] == f"{PREFIX}/status"
    assert state["availability_topic"] == f"{PREFIX}/availability"
    assert state["device"]["name"] == "Mill 1"
    assert alarm["device_class"] == "problem" and alarm["state_topic"] == f"{PREFIX}/status"


async def test_status_follows_a_running_job_and_events_mark_its_start_and_end(
    tmp_path: Path,
) -> None:
    async with (
        mosquitto(tmp_path / "broker") as broker,
        serve(tmp_path, broker, allow_control=True, status_hz=10) as served,
    ):
        (served.jobs_dir / "square.nc").write_text(
            "G21 G90\nG1 X20 F1200\nG1 Y20\nG1 X0\nG1 Y0\n")
        async with watching(broker, f"{PREFIX}/#") as watch:
            await watch.wait_for(f"{PREFIX}/availability", is_online)
            loop = asyncio.get_running_loop()
            started_s, before = loop.time(), len(watch.on(f"{PREFIX}/status"))
            await watch.publish(f"{PREFIX}/cmd/job", {"id": "j1", "name": "square.nc"})
            reply = await watch.wait_json(f"{PREFIX}/reply")
            running = await watch.wait_json(
                f"{PREFIX}/status", lambda s: s["state"] == "Run" and s["job"]["percent"] > 0)
            end = await watch.wait_json(f"{PREFIX}/event/job",
                                        lambda e: e["event"] == "end", timeout_s=20)
            window_s = loop.time() - started_s
            published = len(watch.on(f"{PREFIX}/status")) - before
            done = await watch.wait_json(
                f"{PREFIX}/status", lambda s: s["job"]["state"] == "done")
            events = [event["event"] for event in watch.json_on(f"{PREFIX}/event/job")]
    assert reply == {"id": "j1", "command": "job", "ok": True, "name": "square.nc"}
    assert running["job"]["name"] == "square.nc" and running["job"]["state"] == "running"
    assert running["job"]["remaining_s"] is not None and running["speed_mm_min"] > 0
    assert running["feed_mm_min"] == 1200 and running["mpos"] != [0.0, 0.0]
    assert events == ["start", "end"]
    assert 2 * window_s <= published <= 10 * window_s + 3, "while it moves: at most status_hz"
    assert end["machine"] == "Mill 1" and end["job"]["state"] == "done"
    assert done["job"]["percent"] == 100 and done["mpos"] == [0.0, 0.0]


async def test_control_is_refused_unless_allowed(tmp_path: Path) -> None:
    async with mosquitto(tmp_path / "broker") as broker:
        async with serve(tmp_path, broker) as served, watching(broker, f"{PREFIX}/#") as watch:
            await watch.wait_for(f"{PREFIX}/availability", is_online)
            await watch.publish(f"{PREFIX}/cmd/gcode", {"id": 1, "lines": ["G0 X10"]})
            await watch.publish(f"{PREFIX}/cmd/realtime", "reset")
            await watch.publish(f"{PREFIX}/cmd/job", {"id": "j", "name": "x.nc"})
            replies = [
                await watch.wait_json(f"{PREFIX}/reply", lambda r, c=c: r["command"] == c)
                for c in ("gcode", "realtime", "job")]
            await asyncio.sleep(0.3)
            report = await tcp_report(served.tcp_port)
        async with watching(broker, f"{PREFIX}/availability") as after:  # a clean shutdown
            assert await after.wait_for(f"{PREFIX}/availability") == b"offline"
    assert [r["id"] for r in replies] == [1, None, "j"]
    assert all(r["ok"] is False and r["error"]["reason"] == "control_disabled" for r in replies)
    assert all(r["error"]["code"] == 46 for r in replies)
    assert report.startswith("<Idle|") and mpos(report) == [0.0, 0.0]


async def test_gcode_lines_are_answered_one_to_one_with_their_correlation_id(
    tmp_path: Path,
) -> None:
    batches = {
        "a": ["G21 G90", "G0 X5", "G1 Y2 F600"],
        "b": ["G0 X1", "G999", "G0 X2"],  # the bad line is refused, the others run
        "c": "G0 Y3\nG0 X0 Y0",
    }
    async with (
        mosquitto(tmp_path / "broker") as broker,
        serve(tmp_path, broker, allow_control=True) as served,
        watching(broker, f"{PREFIX}/#") as watch,
    ):
        await watch.wait_for(f"{PREFIX}/availability", is_online)
        for request_id, lines in batches.items():
            await watch.publish(f"{PREFIX}/cmd/gcode", {"id": request_id, "lines": lines})
        await watch.publish(f"{PREFIX}/cmd/gcode", b'{"id": "d", "lines": 7}')
        await watch.publish(f"{PREFIX}/cmd/realtime", {"id": "r", "command": "hold"})
        await watch.wait_json(f"{PREFIX}/reply", lambda r: r["id"] == "c" and r["index"])
        await watch.wait_json(f"{PREFIX}/reply", lambda r: r["id"] == "d")
        await watch.publish(f"{PREFIX}/cmd/realtime", {"id": "s", "command": "resume"})
        await watch.wait_json(f"{PREFIX}/reply", lambda r: r["id"] == "s")
        await asyncio.sleep(0.5)
        replies = watch.json_on(f"{PREFIX}/reply")
        report = await tcp_report(served.tcp_port)
        await watch.publish(f"{PREFIX}/cmd/gcode", {"id": "e", "lines": ["M112"]})
        alarm = await watch.wait_json(f"{PREFIX}/event/alarm")
        status = await watch.wait_json(f"{PREFIX}/status", lambda s: s["alarm"])
    gcode = [r for r in replies if r["command"] == "gcode" and "index" in r]
    assert sorted((r["id"], r["index"]) for r in gcode) == sorted(
        [("a", 0), ("a", 1), ("a", 2), ("b", 0), ("b", 1), ("b", 2), ("c", 0), ("c", 1)])
    by_line = {(r["id"], r["index"]): r for r in gcode}
    assert by_line[("b", 1)]["ok"] is False and by_line[("b", 1)]["error"]["code"] == 20
    assert by_line[("b", 1)]["line"] == "G999"
    assert all(r["ok"] for key, r in by_line.items() if key != ("b", 1))
    invalid = next(r for r in replies if r["id"] == "d")
    assert invalid["error"]["reason"] == "invalid_payload" and "index" not in invalid
    assert {r["id"] for r in replies if r["command"] == "realtime" and r["ok"]} == {"r", "s"}
    assert mpos(report) == [0.0, 0.0]
    assert alarm["machine"] == "Mill 1" and alarm["state"] == "Alarm"
    assert alarm["alarm"]["code"] == 40 and alarm["alarm"]["meaning"].startswith("Halt")
    assert status["state"] == "Alarm" and status["alarm"] == alarm["alarm"]


async def test_a_broker_restart_mid_job_leaves_motion_alone_and_state_is_republished(
    tmp_path: Path,
) -> None:
    job = "G21 G90\nG1 X100 F1500\nG1 X0\n"  # 8 s of motion
    async with (
        mosquitto(tmp_path / "broker") as broker,
        serve(tmp_path, broker, allow_control=True, status_hz=10) as served,
    ):
        (served.jobs_dir / "long.nc").write_text(job)
        async with watching(broker, f"{PREFIX}/#") as watch:
            await watch.wait_for(f"{PREFIX}/availability", is_online)
            await watch.publish(f"{PREFIX}/cmd/job", {"id": 1, "name": "long.nc"})
            await watch.wait_json(f"{PREFIX}/status", lambda s: s["state"] == "Run")
        await broker.stop()
        before = mpos(await tcp_report(served.tcp_port))
        await asyncio.sleep(1.0)
        during = await tcp_report(served.tcp_port)
        await broker.start()  # persistence off: nothing retained until motiond publishes
        async with watching(broker, f"{PREFIX}/#") as watch:
            await watch.wait_for(f"{PREFIX}/availability", is_online, timeout_s=15)
            again = await watch.wait_json(
                f"{PREFIX}/status", lambda s: s["job"] and s["job"]["state"] == "running")
            end = await watch.wait_json(f"{PREFIX}/event/job", lambda e: e["event"] == "end",
                                        timeout_s=30)
        after = await tcp_report(served.tcp_port)
    assert during.startswith("<Run|") and mpos(during) != before, "motion went on"
    assert again["job"]["name"] == "long.nc" and again["state"] == "Run"
    assert end["job"]["state"] == "done" and end["job"]["lines_done"] == 3
    assert after.startswith("<Idle|") and mpos(after) == [0.0, 0.0]


async def test_three_machines_on_one_broker_show_up_in_motiond_fleet(tmp_path: Path) -> None:
    users = {"fleet": "fleet-secret", "m1": "s1", "m2": "s2", "m3": "s3"}
    names = {"m1": "Laser A", "m2": "Laser B", "m3": "Plotter"}
    for user, password in users.items():
        (tmp_path / f"{user}.pw").write_text(password + "\n")
    async with mosquitto(tmp_path / "broker", users=users) as broker, AsyncExitStack() as stack:
        servers: list[Served] = []
        for user, name in names.items():
            folder = tmp_path / user
            folder.mkdir()
            extra = f'[machine]\nname = "{name}"\n' + mqtt_toml(
                broker, username=user, password_file=str(tmp_path / f"{user}.pw"))
            servers.append(await stack.enter_async_context(motiond(folder, extra)))
        async with watching(broker, "motiond/+/availability", username="fleet",
                            password="fleet-secret") as watch:
            for slug in ("laser-a", "laser-b", "plotter"):
                await watch.wait_for(f"motiond/{slug}/availability", is_online)
        servers[2].process.send_signal(signal.SIGKILL)
        await servers[2].process.wait()
        rows = json.loads(await fleet(broker, tmp_path, "--json"))
        text = await fleet(broker, tmp_path)
    assert [(r["machine"], r["availability"], r["state"]) for r in rows] == [
        ("Laser A", "online", "Idle"), ("Laser B", "online", "Idle"),
        ("Plotter", "offline", "Idle")]
    lines = text.splitlines()
    assert lines[0].split() == ["MACHINE", "ONLINE", "STATE", "JOB", "PROGRESS", "REMAINING"]
    assert len(lines) == 4 and "Plotter" in lines[3] and "offline" in lines[3]


async def fleet(broker: Broker, tmp_path: Path, *options: str) -> str:
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.cli", "fleet", "--url", broker.url, "--username", "fleet",
        "--password-file", str(tmp_path / "fleet.pw"), "--wait-s", "0.5", *options,
        cwd=REPO, env=os.environ.copy(), stdout=asyncio.subprocess.PIPE)
    out, _ = await asyncio.wait_for(process.communicate(), 30)
    assert process.returncode == 0
    return out.decode()


async def test_cmd_job_refuses_a_job_that_does_not_fit_and_nothing_moves(tmp_path: Path) -> None:
    async with (
        mosquitto(tmp_path / "broker") as broker,
        serve(tmp_path, broker, allow_control=True) as served,
    ):
        (served.jobs_dir / "neg.nc").write_text("G21 G90\nG1 X-12.5 Y40 F3000\nG1 X0 Y0\n")
        async with watching(broker, f"{PREFIX}/#") as watch:
            await watch.wait_for(f"{PREFIX}/availability", is_online)
            await watch.publish(f"{PREFIX}/cmd/job", {"id": "j", "name": "neg.nc"})
            reply = await watch.wait_json(f"{PREFIX}/reply")
            await asyncio.sleep(0.3)
            report = await tcp_report(served.tcp_port)
    assert reply["ok"] is False and reply["error"]["code"] == 47
    assert "X: 12.500 mm below the travel's minimum" in reply["error"]["message"]
    assert "X work origin between 12.500 and 300.000" in reply["error"]["message"]
    assert report.startswith("<Idle|") and mpos(report) == [0.0, 0.0]
