"""Stop means stop for G-code queued on the JSON API and on MQTT too (issue #36): lines asked
for before a stop never run after it, whichever path they wait on.

A browser-like client pipelines ``gcode.send`` requests on one ``/api`` WebSocket (each waits
its turn behind the one before), or a broker client publishes one ``cmd/gcode`` message of
many lines (the ``[mqtt]`` module runs them one after another); the operator then holds and
resets the machine from a TCP connection, as in tests/e2e/test_one_stop.py. The laser machine
of :mod:`tests.support.stop_rig` is served in this process (real ports, a real Mosquitto
broker, the real clock); what it did is read from the simulated backend's steps and laser
output.
"""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

from tests.support.api_client import client
from tests.support.broker import mosquitto, watching
from tests.support.stop_rig import BANNER, Rig, stop_rig

MOVES = 30  # 3 s of cutting at F600; the planner takes 0.5 s of it, the rest waits
PREFIX = "motiond/stops"


def cuts() -> list[str]:
    return [f"G1 X{1 + i} F600 M3 S1000" for i in range(MOVES)]


async def hold_then_reset(rig: Rig) -> None:
    """The operator's ``!``, once held ``Ctrl-X``, from a TCP connection of its own."""
    operator = await rig.tcp()
    operator.send(b"!")
    await operator.wait_state("Hold:0")
    operator.send(b"\x18")
    await operator.until(lambda got: got.count(BANNER) == 2)


async def test_gcode_send_requests_waiting_on_the_json_api_never_run_after_a_hold_and_reset(
        tmp_path: Path) -> None:
    async with stop_rig(tmp_path) as rig, client(rig.http) as browser:
        calls = [asyncio.create_task(browser.request("gcode.send", lines=[line]))
                 for line in cuts()]
        try:
            await rig.moving()
            assert rig.laser_fired_since(0), "the lines cut"
            await hold_then_reset(rig)
            waiting = [call for call in calls if not call.done()]
            await rig.assert_still(1.5, "after the reset")
            answers = [await asyncio.wait_for(call, 5) for call in waiting]
        finally:
            for call in calls:
                call.cancel()
    assert len(waiting) > MOVES // 2, "most requests were still waiting when the stop came"
    lines = [answer["result"]["results"][0] for answer in answers]
    assert all(line.get("error", {}).get("code") == 45 for line in lines), lines


async def test_an_mqtt_gcode_message_stops_with_a_hold_and_reset_from_another_connection(
        tmp_path: Path) -> None:
    mqtt = {"allow_control": True, "topic_prefix": PREFIX}
    async with contextlib.AsyncExitStack() as stack:
        broker = await stack.enter_async_context(mosquitto(tmp_path / "broker"))
        rig = await stack.enter_async_context(
            stop_rig(tmp_path, mqtt={"url": broker.url, **mqtt}))
        watch = await stack.enter_async_context(watching(broker, f"{PREFIX}/#"))
        await watch.wait_for(f"{PREFIX}/availability", lambda payload: payload == b"online")
        await watch.publish(f"{PREFIX}/cmd/gcode", {"id": "cut", "lines": cuts()})
        await rig.moving()
        assert rig.laser_fired_since(0), "the lines cut"
        await hold_then_reset(rig)
        answered = len(watch.json_on(f"{PREFIX}/reply"))
        await rig.assert_still(1.5, "after the reset")
        await watch.wait_json(f"{PREFIX}/reply", lambda reply: reply["index"] == MOVES - 1)
        replies: list[dict[str, Any]] = watch.json_on(f"{PREFIX}/reply")
    assert answered < MOVES // 2, "most lines were still waiting when the stop came"
    after = replies[answered:]
    assert [reply["index"] for reply in after] == list(range(answered, MOVES))
    assert all(not reply["ok"] and reply["error"]["code"] == 45 for reply in after), after
