"""The JSON API at /api, over a real WebSocket client (aiohttp's) and real TCP ports."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from server.api.server import API_KEY, JsonApi
from server.runtime.clock import RealClock
from tests.conftest import CORPUS
from tests.support import websocket_client as wsc
from tests.support.api_client import api_config, client, http_of, serving

SQUARE = "G21 G90\nG0 X10 Y10\nG1 X30 F6000\nG1 Y30\nG1 X10\nG1 Y10\nG0 X12 Y14\n"


def state_is(*states: str) -> Any:
    return lambda params: params["status"]["state"] in states


def moving(params: dict[str, Any]) -> bool:
    return bool(params["status"]["moving"]) and params["status"]["mpos"][0] > 0


# -- server and protocol ----------------------------------------------------------------------
async def test_server_info_names_the_machine_axes_and_every_method(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        info = await rpc.call("server.info")
    assert info["name"] == "motiond" and info["can_control"] is True
    assert [axis["name"] for axis in info["axes"]] == ["X", "Y", "Z"]
    assert {"gcode.send", "machine.subscribe", "job.toolpath", "settings.set"} <= set(
        info["methods"]
    )
    assert info["upload"]["url"] == "/upload"


async def test_protocol_errors_are_answered_with_json_rpc_codes(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        await rpc.connection.send("{not json")
        await rpc.connection.send(json.dumps([{"jsonrpc": "2.0", "id": 1, "method": "x"}]))
        unknown = await rpc.error("machine.fly")
        bad = await rpc.error("machine.jog", x="far", feed_mm_min=100)
        missing = await rpc.error("machine.jog", x=1)
        async with asyncio.timeout(5):
            while len(rpc.notifications) < 2:
                rpc.arrived.clear()
                await rpc.arrived.wait()
    parse, batch = rpc.notifications[:2]  # replies with a null id
    assert parse["error"]["code"] == -32700 and parse["id"] is None
    assert batch["error"]["code"] == -32600
    assert unknown["code"] == -32601
    assert bad["code"] == -32602 and "x" in bad["message"]
    assert missing["code"] == -32602 and "feed_mm_min" in missing["message"]


async def test_a_notification_request_runs_without_a_reply(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        await rpc.connection.send(
            json.dumps({"jsonrpc": "2.0", "method": "gcode.send", "params": {"lines": "G92 X7"}})
        )
        await asyncio.sleep(0.2)
        status = await rpc.call("machine.status")
    assert status["wpos"][0] == 7.0
    assert rpc.notifications == []


# -- G-code and control -----------------------------------------------------------------------
async def test_gcode_send_answers_every_line_in_order_and_stops_at_the_first_error(
    tmp_path: Path,
) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        sent = await rpc.call("gcode.send", lines=["G21", "$G", "G1 X5 F600", "G99", "G0 X1"])
        all_sent = await rpc.call("gcode.send", lines="G77\nG0 X2", stop_on_error=False)
        query = await rpc.call("gcode.send", lines="?")
    replies = [result["reply"] for result in sent["results"]]
    assert replies == ["ok", "ok", "ok", "error:20"] and sent["skipped"] == 1
    assert sent["results"][1]["messages"][0].startswith("[GC:G0 G54")
    error = sent["results"][3]["error"]
    assert error["code"] == 20 and error["meaning"] == "Unsupported or invalid G-code command"
    assert [r["reply"] for r in all_sent["results"]] == ["error:20", "ok"]
    assert query["results"][0]["messages"][0].startswith("<")


async def test_jog_moves_the_machine_by_the_step_size(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["status"])
        await rpc.call("machine.jog", x=10, y=-0.0, feed_mm_min=6000)
        await rpc.call("machine.jog", y=2.5, feed_mm_min=6000)
        params = await rpc.wait_for(
            "notify_status_update",
            lambda p: p["status"]["mpos"][:2] == [10.0, 2.5] and p["status"]["state"] == "Idle",
        )
    assert params["status"]["wpos"][:2] == [10.0, 2.5]


async def test_status_subscribers_see_the_machine_run_and_come_to_rest(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path), RealClock()) as (app, address), client(address) as rpc:
        subscribed = await rpc.call("machine.subscribe")
        assert subscribed["status"]["state"] == "Idle"
        await rpc.call("gcode.send", lines="G1 X20 F3000")
        running_status = await rpc.wait_for("notify_status_update", moving)
        telemetry = await rpc.wait_for("notify_telemetry", lambda p: p["speed_mm_min"] > 0)
        rest = await rpc.wait_for(
            "notify_status_update",
            lambda p: p["status"]["state"] == "Idle" and p["status"]["mpos"][0] == 20.0,
        )
    assert running_status["status"]["state"] == "Run"
    assert 0 < telemetry["speed_mm_min"] <= 3000.5
    assert rest["status"]["speed_mm_min"] == 0.0 and rest["status"]["queue_depth"] == 0


async def test_hold_stops_the_move_and_resume_finishes_it(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path), RealClock()) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["status"])
        await rpc.call("gcode.send", lines="G1 X60 F3000")
        await rpc.wait_for("notify_status_update", moving)
        await rpc.call("machine.hold")
        held = await rpc.wait_for("notify_status_update", state_is("Hold:0"))
        await asyncio.sleep(0.2)
        still = await rpc.call("machine.status")
        await rpc.call("machine.resume")
        done = await rpc.wait_for(
            "notify_status_update",
            lambda p: p["status"]["state"] == "Idle" and p["status"]["mpos"][0] == 60.0,
        )
    assert 0.0 < held["status"]["mpos"][0] < 60.0
    assert still["mpos"] == held["status"]["mpos"] and still["state"] == "Hold:0"
    assert done["status"]["alarm"] is None


async def test_m410_from_another_client_stops_the_move_on_arrival_without_an_alarm(
    tmp_path: Path,
) -> None:
    async with serving(api_config(tmp_path), RealClock()) as (app, address), \
            client(address) as rpc, client(address) as other:
        await rpc.call("machine.subscribe", topics=["status"])
        await rpc.call("gcode.send", lines="G1 X60 F600")
        await rpc.wait_for("notify_status_update", moving)
        stopped = await other.call("gcode.send", lines="M410")
        status = await rpc.call("machine.status")
        await asyncio.sleep(0.3)
        still = await rpc.call("machine.status")
    assert stopped["results"][0]["reply"] == "ok", "not refused as another's motion (45)"
    assert status["state"] == "Idle" and status["alarm"] is None
    assert 0.0 < still["mpos"][0] < 60.0 and still["mpos"] == status["mpos"]


async def test_reset_while_moving_alarms_with_its_meaning_until_unlocked(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path), RealClock()) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["status", "console"])
        await rpc.call("gcode.send", lines="G1 X60 F3000")
        await rpc.wait_for("notify_status_update", moving)
        await rpc.call("machine.reset")
        alarm = await rpc.wait_for("notify_status_update", state_is("Alarm"))
        pushed = await rpc.wait_for("notify_gcode_response", lambda p: p["message"] == "ALARM:3")
        locked = await rpc.call("gcode.send", lines="G0 X1")
        await rpc.call("machine.unlock")
        idle = await rpc.wait_for("notify_status_update", state_is("Idle"))
    assert alarm["status"]["alarm"]["code"] == 3
    assert "position may be lost" in alarm["status"]["alarm"]["meaning"]
    assert pushed["message"] == "ALARM:3"
    assert locked["results"][0]["error"]["code"] == 9
    assert idle["status"]["alarm"] is None


async def test_estop_and_the_laser_fire_command(tmp_path: Path) -> None:
    config = api_config(tmp_path, laser={})
    async with serving(config) as (app, address), client(address) as rpc:
        fired = await rpc.call("laser.fire", percent=5, duration_s=2)
        power = (await rpc.call("machine.status"))["power_pct"]
        await rpc.call("laser.off")
        await rpc.call("machine.estop")
        status = await rpc.call("machine.status")
    assert fired["messages"] == ["[MSG:fire 5% for at most 2s]"]
    assert power == 5.0
    assert status["state"] == "Alarm" and status["alarm"]["code"] == 40 and status["power_pct"] == 0


async def test_home_runs_the_homing_cycle_and_is_refused_without_endstops(tmp_path: Path) -> None:
    switches = {"switch_at_mm": -5, "seek_mm_s": 100}
    config = api_config(tmp_path, endstops={"axes": {"x": switches, "y": switches}})
    async with serving(config, RealClock()) as (app, address), client(address) as rpc:
        info = await rpc.call("server.info")
        await rpc.call("machine.estop")
        homed = await rpc.call("machine.home")
    assert "homing" in info["features"]
    assert homed == {"state": "Idle", "messages": ["[MSG:Homed XY]"]}
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        refused = await rpc.error("machine.home")
    assert refused["code"] == 5 and "homing is not configured" in refused["message"]


async def test_settings_are_listed_and_written_through_the_dollar_command(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        written = await rpc.call("settings.set", number=110, value=24000)
        listed = {s["number"]: s for s in await rpc.call("settings.list")}
        refused = await rpc.error("settings.set", number=999, value=1)
    assert written == {"number": 110, "value": 24000.0}
    assert listed[110]["value"] == 24000.0 and listed[110]["writable"]
    assert refused["code"] == 3 and refused["data"]["meaning"] == "Invalid $ statement"
    assert app.kernel.config.core.axes["x"].max_rate_mm_s == 400.0


# -- jobs -------------------------------------------------------------------------------------
async def test_an_uploaded_job_runs_to_the_end_with_progress_updates(tmp_path: Path) -> None:
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["job", "status"])
        async with aiohttp.ClientSession() as http:
            reply = await http.post(f"http://{address}/upload?name=square.nc", data=SQUARE)
            stored = await reply.json()
            bad = await http.post(f"http://{address}/upload?name=../x.nc", data=b"G0")
            bad_body = await bad.json()
        files = await rpc.call("job.list")
        started = await rpc.call("job.start", name="square.nc")
        done = await rpc.wait_for("notify_job_update", lambda p: p["job"]["state"] == "done")
        status = await rpc.call("machine.status")
        progress = await rpc.call("job.progress")
    assert reply.status == 200 and stored["result"]["size_bytes"] == len(SQUARE)
    assert bad.status == 400 and bad_body["error"]["code"] == 44
    assert "square.nc" in [f["name"] for f in files]
    assert started["state"] == "running" and started["name"] == "square.nc"
    assert done["job"]["percent"] == 100.0 and progress["state"] == "done"
    assert status["wpos"][:2] == [12.0, 14.0] and status["state"] == "Idle"


async def test_job_controls_pause_resume_and_abort_a_running_job(tmp_path: Path) -> None:
    (tmp_path / "jobs").mkdir()
    (tmp_path / "jobs" / "long.nc").write_text("G1 X100 F3000\nG1 X0\n")
    async with serving(api_config(tmp_path), RealClock()) as (app, address), client(address) as rpc:
        await rpc.call("machine.subscribe", topics=["job", "status"])
        await rpc.call("job.start", name="long.nc")
        await rpc.wait_for("notify_status_update", moving)
        paused = await rpc.call("job.pause")
        await rpc.wait_for("notify_status_update", state_is("Hold:0"))
        resumed = await rpc.call("job.resume")
        await rpc.wait_for("notify_status_update", state_is("Run"))
        aborted = await rpc.call("job.abort")
        busy = await rpc.error("job.start", name="missing.nc")
    assert paused["state"] == "paused" and resumed["state"] == "running"
    assert aborted["state"] == "aborted"
    assert busy["code"] == 44


async def test_upload_over_the_socket_and_the_planned_toolpath_of_a_corpus_job(
    tmp_path: Path,
) -> None:
    text = (CORPUS / "laser-vector-jsdc.gcode").read_text()
    async with serving(api_config(tmp_path)) as (app, address), client(address) as rpc:
        await rpc.call("job.upload", name="jsdc.gcode", text=text)
        path = await rpc.call("job.toolpath", name="jsdc.gcode")
        small = await rpc.call("job.toolpath", name="jsdc.gcode", max_segments=150)
        deleted = await rpc.call("job.delete", name="jsdc.gcode")
        gone = await rpc.error("job.toolpath", name="jsdc.gcode")
    assert path["error"] is None and 100 < path["segments"] <= 50_000
    assert len(path["points"]) == 2 * (path["segments"] + 1)
    assert len(path["kinds"]) == len(path["speeds"]) == len(path["powers"]) == path["segments"]
    assert path["bounds"]["min"][1] < -50 and path["bounds"]["max"][0] > 100
    assert max(path["powers"]) > 0 and path["duration_s"] > 100
    assert small["segments"] <= 150 and small["end"] == path["end"]
    assert deleted == {"deleted": "jsdc.gcode"} and gone["code"] == 44


# -- fan-out, slow subscribers, access --------------------------------------------------------
async def test_updates_are_rate_limited_and_encoded_once_for_all_subscribers(
    tmp_path: Path,
) -> None:
    async with (
        serving(api_config(tmp_path), RealClock()) as (app, address),
        client(address) as first,
        client(address) as second,
    ):
        api: JsonApi = http_of(app).app[API_KEY]
        await first.call("machine.subscribe")
        await second.call("machine.subscribe")
        await asyncio.sleep(0.2)
        encoded_before, counts_before = (
            api.publisher.encoded,
            (len(first.notifications), len(second.notifications)),
        )
        await first.call("gcode.send", lines="G1 X50 F3000")  # one second of motion
        await first.wait_for("notify_status_update", lambda p: p["status"]["mpos"][0] == 50.0)
        await asyncio.sleep(0.3)
        encoded = api.publisher.encoded - encoded_before
        received = (
            len(first.notifications) - counts_before[0],
            len(second.notifications) - counts_before[1],
        )
    statuses = [
        m for m in first.notifications[counts_before[0] :] if m["method"] == "notify_status_update"
    ]
    assert received[0] == received[1] == encoded, "one encoding per update, sent to everyone"
    assert 10 <= len(statuses) <= 1.6 * 20 + 4, "at most 20 status updates a second"


async def test_a_subscriber_that_stops_reading_is_dropped_and_the_others_keep_going(
    tmp_path: Path,
) -> None:
    async with serving(api_config(tmp_path)) as (app, address):
        api: JsonApi = http_of(app).app[API_KEY]
        small = {"receive_buffer_bytes": 4096}
        async with client(address, **small) as stalled, client(address) as reader:
            await stalled.call("machine.subscribe", topics=["console"])
            await reader.call("machine.subscribe", topics=["console"])
            stalled._reader.cancel()  # noqa: SLF001 - this client stops reading now
            message = "[MSG:" + "x" * 16_000 + "]"
            for _ in range(2000):
                app.kernel.push(message)
                await asyncio.sleep(0)
                if api.publisher.dropped:
                    break
            app.kernel.push("[MSG:last]")
            last = await reader.wait_for(
                "notify_gcode_response", lambda p: p["message"] == "[MSG:last]"
            )
        assert api.publisher.dropped == 1
        assert last["message"] == "[MSG:last]"
        assert len(api.connections) == 0 or all(not c.channel.overflowed for c in api.connections)


async def test_a_token_makes_connections_read_only_until_they_authenticate(tmp_path: Path) -> None:
    config = api_config(tmp_path, http={"port": 0, "token": "s3cret"})
    async with serving(config) as (app, address), client(address) as rpc:
        info = await rpc.call("server.info")
        refused = await rpc.call("gcode.send", lines="G0 X1")
        hold = await rpc.error("machine.hold")
        wrong = await rpc.error("server.auth", token="guess")
        await rpc.call("server.auth", token="s3cret")
        accepted = await rpc.call("gcode.send", lines="G0 X1")
        async with aiohttp.ClientSession() as http:
            upload = await http.post(f"http://{address}/upload?name=a.nc", data=b"G0 X1")
            with_token = await http.post(
                f"http://{address}/upload?name=a.nc&token=s3cret", data=b"G0 X1"
            )
        async with client(address, "/api?token=s3cret") as trusted:
            assert (await trusted.call("server.info"))["can_control"] is True
    assert info["can_control"] is False and info["auth_required"] is True
    assert refused["results"][0]["error"]["code"] == 46
    assert hold["code"] == 46 and wrong["code"] == 46
    assert accepted["results"][0]["reply"] == "ok"
    assert upload.status == 401 and with_token.status == 200


async def test_a_page_from_another_origin_is_refused(tmp_path: Path) -> None:
    config = api_config(tmp_path, http={"port": 0, "allowed_origins": ["http://ui.example"]})
    async with serving(config) as (app, address):
        with pytest.raises(wsc.InvalidStatus) as refused:
            await wsc.connect(f"ws://{address}/api", origin="http://evil.example")
        async with (
            client(address, origin="http://ui.example") as listed,
            client(address, origin=f"http://{address}") as same,
        ):
            assert (await listed.call("machine.status"))["state"] == "Idle"
            assert (await same.call("machine.status"))["state"] == "Idle"
    assert refused.value.response.status_code == 403
