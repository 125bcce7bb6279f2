"""Retained MQTT commands never move the machine (real Mosquitto, real ``motiond``).

A command published with the retain flag (one mistaken ``mosquitto_pub -r``, a Node-RED or
Home Assistant publish with retain set) used to run again at every start and every broker
reconnect. Now: with MQTT 5 the broker does not send it at all when motiond subscribes, and
one published while motiond listens is refused naming why; with MQTT 3.1.1 the stored message
is refused once, and not answered again after a reconnect (a 3.1.1 broker clears the flag on
a message it forwards live, so there a retained publish runs once, as it is published, and
never again). A plain command still runs (the
test's control), and replies and events are never retained.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import aiomqtt
import pytest

from tests.e2e.test_mqtt import MACHINE, PREFIX, is_online, mpos, tcp_report
from tests.support.broker import Broker, Watcher, mosquitto, mqtt_toml, watching
from tests.support.processes import latency_probe, motiond
from tests.support.undisturbed import assert_prompt

CLIENT_ID = "motiond-mill-1"
MOVE = {"id": "stored", "lines": ["G0 X123 Y45"]}
JOB = {"id": "stored-job", "name": "cut.nc"}


async def publish_retained(broker: Broker, topic: str, payload: object) -> None:
    async with aiomqtt.Client("127.0.0.1", broker.port) as client:
        await client.publish(topic, json.dumps(payload), qos=1, retain=True)


async def kick_motiond(broker: Broker, watch: Watcher) -> None:
    """A broker blip as motiond sees it: another client takes its client id (the broker drops
    motiond's connection), then leaves; wait until motiond is back online."""
    seen = len(watch.on(f"{PREFIX}/availability"))
    async with aiomqtt.Client("127.0.0.1", broker.port, identifier=CLIENT_ID):
        await asyncio.sleep(0.2)
    async with asyncio.timeout(15):
        while not any(is_online(p) for p in watch.on(f"{PREFIX}/availability")[seen:]):
            watch.arrived.clear()
            await watch.arrived.wait()


async def retained_on(broker: Broker, *topics: str) -> list[str]:
    """The topics among ``topics`` (filters) the broker holds a retained message for."""
    found: list[str] = []
    async with aiomqtt.Client("127.0.0.1", broker.port) as client:
        for topic in topics:
            await client.subscribe(topic, 1)
        with pytest.raises(TimeoutError):
            async with asyncio.timeout(1.0):
                async for message in client.messages:
                    found.append(str(message.topic))
    return found


def retained_replies(watch: Watcher) -> list[dict[str, object]]:
    return [r for r in watch.json_on(f"{PREFIX}/reply") if r["id"] in ("stored", "stored-job",
                                                                       "live")]


@pytest.mark.parametrize("protocol", ["5", "3.1.1"])
async def test_retained_commands_never_run_at_start_or_after_a_reconnect(
    tmp_path: Path, protocol: str,
) -> None:
    async with mosquitto(tmp_path / "broker") as broker:
        await publish_retained(broker, f"{PREFIX}/cmd/gcode", MOVE)
        await publish_retained(broker, f"{PREFIX}/cmd/job", JOB)
        toml = MACHINE + mqtt_toml(broker, allow_control=True, protocol=protocol)
        async with (
            watching(broker, f"{PREFIX}/#") as watch,
            motiond(tmp_path, toml) as served,
            latency_probe(served.tcp_port) as probe,
        ):
            (served.jobs_dir / "cut.nc").write_text("G0 X100\n")
            await watch.wait_for(f"{PREFIX}/availability", is_online, timeout_s=15)
            await asyncio.sleep(2.0)  # what the stored messages did within 3 s, before
            at_start = await tcp_report(served.tcp_port)
            first = retained_replies(watch)
            await kick_motiond(broker, watch)
            await asyncio.sleep(1.5)
            after_reconnect = retained_replies(watch)
            refused_live = None
            if protocol == "5":  # 3.1.1 brokers clear the flag on messages sent live
                live = {"id": "live", "lines": ["G0 X77"]}
                await watch.client.publish(f"{PREFIX}/cmd/gcode", json.dumps(live), 1,
                                           retain=True)
                refused_live = await watch.wait_json(f"{PREFIX}/reply",
                                                     lambda r: r["id"] == "live")
            await watch.publish(f"{PREFIX}/cmd/gcode", {"id": "plain", "lines": ["G0 X5"]})
            plain = await watch.wait_json(f"{PREFIX}/reply", lambda r: r["id"] == "plain")
            await asyncio.sleep(1.0)
            end = await tcp_report(served.tcp_port)
            kept = await retained_on(broker, f"{PREFIX}/reply", f"{PREFIX}/event/#")
    assert at_start.startswith("<Idle|") and mpos(at_start) == [0.0, 0.0], at_start
    if protocol == "5":
        assert first == [], "MQTT 5: the broker sends no stored command on subscribing"
    else:
        assert sorted(str(r["id"]) for r in first) == ["stored", "stored-job"]
        assert all(r["ok"] is False and r["error"]["reason"] == "retained"  # type: ignore[index]
                   for r in first)
        assert "retain" in str(first[0]["error"]["message"])  # type: ignore[index]
    assert after_reconnect == first, "not answered again after a reconnect"
    if refused_live is not None:
        assert refused_live["ok"] is False and refused_live["error"]["reason"] == "retained"
    assert plain["ok"] is True
    assert mpos(end) == [5.0, 0.0], end
    assert kept == [], "replies and events are never retained"
    assert_prompt(probe)  # the operator's ? stayed prompt through starts and reconnects
