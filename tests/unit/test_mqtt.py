"""The pure parts of ``[mqtt]``: config, topics, payloads, discovery, outbox, fleet table."""

from __future__ import annotations

import asyncio
import json
from types import SimpleNamespace
from typing import Any

import pytest

from modules.mqtt.config import BrokerAddress, Topics, broker_address, slug
from modules.mqtt.control import Control
from modules.mqtt.discovery import Device, discovery_messages
from modules.mqtt.fleet import Machine, absorb, table
from modules.mqtt.module import _job_event
from modules.mqtt.outbox import Outbox, Outgoing
from modules.mqtt.payloads import (
    Gcode,
    Invalid,
    Realtime,
    StartJob,
    parse_request,
    status_payload,
)
from server.errors import CommandError, ConfigError, Error
from tests.conftest import REPO, make_config


@pytest.mark.parametrize(("url", "address"), [
    ("mqtt://broker", BrokerAddress("broker", 1883, False)),
    ("MQTTS://broker.example.com", BrokerAddress("broker.example.com", 8883, True)),
    ("mqtt://127.0.0.1:11883/", BrokerAddress("127.0.0.1", 11883, False)),
    ("mqtts://[::1]:8884", BrokerAddress("::1", 8884, True)),
])
def test_broker_urls(url: str, address: BrokerAddress) -> None:
    assert broker_address(url) == address


@pytest.mark.parametrize(("url", "why"), [
    ("http://broker:1883", "mqtt:// or mqtts://"), ("broker:1883", "mqtt:// or mqtts://"),
    ("mqtt://user:pw@broker", "credentials"), ("mqtt://broker:99999", "invalid port"),
    ("mqtt://broker/topic", "without a path"), ("mqtt://:1883", "no host"),
])
def test_bad_broker_urls_say_why(url: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        broker_address(url)


@pytest.mark.parametrize(("section", "problem"), [
    ({"url": "http://x"}, "test.toml: [mqtt] url: the scheme must be mqtt:// or mqtts://"),
    ({"url": "mqtt://x", "qos": 3}, "test.toml: [mqtt] qos: Input should be less than or equal"),
    ({"url": "mqtt://x", "topic_prefix": "a/#"}, "test.toml: [mqtt] topic_prefix: a topic prefix"),
    ({"url": "mqtt://x", "topic_prefix": "a//b"}, "test.toml: [mqtt] topic_prefix: empty topic"),
    ({"url": "mqtt://x", "password": "p"}, "test.toml: [mqtt]: a password needs a username"),
    ({"url": "mqtt://x", "ca_file": "/etc/hostname"}, "test.toml: [mqtt]: ca_file needs an mqtts://"),
    ({"url": "mqtt://x", "status_hz": 0}, "test.toml: [mqtt] status_hz: Input should be greater"),
    ({"url": "mqtt://x", "colour": "red"}, "test.toml: [mqtt] colour: unknown key"),
    ({}, "test.toml: [mqtt] url: missing required value"),
])
def test_bad_config_names_file_section_and_key(section: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError) as raised:
        make_config({"mqtt": section})
    assert any(line.startswith(problem) for line in raised.value.problems), raised.value.problems


def test_slugs_and_topics() -> None:
    assert slug("Laser #2 (shop)") == "laser-2-shop" and slug("!!!") == "motiond"
    topics = Topics("motiond/laser-2")
    assert topics.commands == "motiond/laser-2/cmd/+"
    assert topics.command_of("motiond/laser-2/cmd/gcode") == "gcode"
    assert topics.command_of("motiond/laser-22/cmd/gcode") is None
    assert topics.event("alarm") == "motiond/laser-2/event/alarm"


@pytest.mark.parametrize(("command", "payload", "parsed"), [
    ("gcode", b'{"id": "a", "lines": ["G0 X1", "G1 X2 F9"]}', Gcode("a", ("G0 X1", "G1 X2 F9"))),
    ("gcode", b'{"id": 7, "lines": "G0 X1\\nG0 X2"}', Gcode(7, ("G0 X1", "G0 X2"))),
    ("realtime", b"hold\n", Realtime(None, "hold")),
    ("realtime", b'{"id": "r", "command": "reset"}', Realtime("r", "reset")),
    ("job", b'{"id": "j", "name": "part.nc"}', StartJob("j", "part.nc")),
])
def test_requests(command: str, payload: bytes, parsed: object) -> None:
    assert parse_request(command, payload, max_lines=10) == parsed


@pytest.mark.parametrize(("command", "payload", "request_id", "why"), [
    ("gcode", b"\xff", None, "not UTF-8"),
    ("gcode", b"G0 X10", None, "JSON object"),
    ("gcode", b"[" * 10_000, None, "JSON object"),
    ("gcode", b'{"lines": ["G0"]}', None, "id"),
    ("gcode", b'{"id": true, "lines": ["G0"]}', None, "id"),
    ("gcode", b'{"id": "x", "lines": []}', "x", "empty"),
    ("gcode", b'{"id": "x", "lines": ["G0", 1]}', "x", "lines"),
    ("gcode", b'{"id": "x", "lines": ["G0\\u0018"]}', "x", "control character"),
    ("gcode", b'{"id": "x", "lines": ["G0\\nG1"]}', "x", "line break"),
    ("gcode", json.dumps({"id": 3, "lines": ["G0"] * 11}).encode(), 3, "at most 10 lines"),
    ("gcode", b'{"id": "x", "lines": ["G0"], "more": 1}', "x", "more"),
    ("realtime", b'{"id": "r", "command": "explode"}', "r", "command"),
    ("realtime", b"HOLD", None, "JSON object"),
    ("job", b'{"id": "j", "name": ""}', "j", "name"),
    ("job", b'{"id": "j"}', "j", "name"),
    ("nope", b'{"id": "n"}', "n", "unknown command topic"),
])
def test_malformed_requests_are_refused_whole_keeping_the_id(
    command: str, payload: bytes, request_id: object, why: str
) -> None:
    refused = parse_request(command, payload, max_lines=10)
    assert isinstance(refused, Invalid) and refused.id == request_id
    assert why in refused.message


SNAPSHOT = {
    "state": "Run", "alarm": None, "mpos": [1.0, 2.0], "wpos": [1.0, 2.0], "wco": [0.0, 0.0],
    "speed_mm_min": 600.0, "power_pct": 40.0, "tool": {"mode": "M4", "s": 400.0},
    "moving": True, "queue_depth": 3, "line": 12, "overrides": {"feed": 100},
    "modal": {"feed_mm_min": 900.0, "units": "mm"}, "modules": {"laser": {}},
    "job": {"name": "a.nc", "state": "running", "percent": 42.0, "remaining_s": 30.0},
}


def test_the_status_payload_is_the_json_status_cut_for_a_dashboard() -> None:
    payload = status_payload(SNAPSHOT, "Laser 1")
    assert payload["machine"] == "Laser 1" and payload["feed_mm_min"] == 900.0
    assert payload["job"]["percent"] == 42.0 and payload["state"] == "Run"
    assert "modal" not in payload and "modules" not in payload and "moving" not in payload


def test_home_assistant_discovery() -> None:
    topics, device = Topics("motiond/laser-1"), Device("laser-1", "Laser 1", "0.1.0")
    configs = dict(discovery_messages(topics, device, "homeassistant", allow_control=False))
    state = configs["homeassistant/sensor/laser-1/state/config"]
    alarm = configs["homeassistant/binary_sensor/laser-1/alarm/config"]
    progress = configs["homeassistant/sensor/laser-1/progress/config"]
    assert state is not None and alarm is not None and progress is not None
    assert state["state_topic"] == "motiond/laser-1/status"
    assert state["availability_topic"] == "motiond/laser-1/availability"
    assert state["unique_id"] == "motiond_laser-1_state"
    assert state["device"]["identifiers"] == ["motiond_laser-1"]
    assert alarm["device_class"] == "problem" and progress["unit_of_measurement"] == "%"
    assert configs["homeassistant/button/laser-1/hold/config"] is None  # removed
    allowed = dict(discovery_messages(topics, device, "homeassistant", allow_control=True))
    button = allowed["homeassistant/button/laser-1/reset/config"]
    assert button is not None and button["payload_press"] == "reset"
    assert button["command_topic"] == "motiond/laser-1/cmd/realtime"


def test_the_outbox_keeps_the_latest_status_and_drops_the_oldest_messages() -> None:
    outbox = Outbox(limit=2)
    outbox.put_status(Outgoing("s", b"1", True))
    outbox.put_status(Outgoing("s", b"2", True))
    for number in range(3):
        outbox.put(Outgoing("r", str(number).encode()))
    assert [m.payload for m in iter(outbox.take, None)] == [b"1", b"2", b"2"]
    assert outbox.stale == 1 and outbox.dropped == 1
    outbox.restore_status(Outgoing("s", b"3", True))
    outbox.put_status(Outgoing("s", b"4", True))
    outbox.restore_status(Outgoing("s", b"3", True))  # a newer one is there: ignored
    assert outbox.take() == Outgoing("s", b"4", True) and outbox.take() is None


@pytest.mark.parametrize(("previous", "state", "event"), [
    (None, "running", "start"), ("running", "paused", "pause"), ("paused", "running", "resume"),
    ("running", "done", "end"), ("paused", "aborted", "end"), (None, "failed", "end"),
    ("running", "running", None), ("done", "done", None),
])
def test_job_events(previous: str | None, state: str, event: str | None) -> None:
    assert _job_event(previous, state) == event


def test_the_fleet_table() -> None:
    machines: dict[str, Machine] = {}
    absorb(machines, "motiond", "motiond/laser-1/availability", b"online")
    absorb(machines, "motiond", "motiond/laser-1/status", json.dumps(
        {"machine": "Laser 1", **SNAPSHOT}).encode())
    absorb(machines, "motiond", "motiond/mill/availability", b"offline")
    absorb(machines, "motiond", "motiond/mill/status", b"{broken")
    absorb(machines, "motiond", "motiond/cnc/status", json.dumps({"state": "Alarm", "alarm": {
        "code": 1, "message": "x", "meaning": "Hard limit triggered"}, "job": None}).encode())
    absorb(machines, "motiond", "other/x/status", b"{}")
    absorb(machines, "motiond", "motiond/x/reply", b"{}")
    rows = [machine.row() for machine in machines.values()]
    assert [row["machine"] for row in rows] == ["Laser 1", "mill", "cnc"]
    assert rows[2]["alarm"] == "Hard limit triggered" and rows[2]["availability"] == "unknown"
    assert rows[0]["progress_pct"] == 42.0 and rows[0]["job"] == "a.nc"
    lines = table(rows).splitlines()
    assert lines[0].split() == ["MACHINE", "ONLINE", "STATE", "JOB", "PROGRESS", "REMAINING"]
    assert lines[1].split() == ["Laser", "1", "online", "Run", "a.nc", "42", "%", "0:30"]
    assert lines[2].split() == ["mill", "offline", "-", "-", "-", "-"]
    assert lines[3].split() == ["cnc", "unknown", "Alarm", "1", "-", "-", "-"]
    assert table([]) == "no machines found"


class FakeContext:
    """Just what :class:`Control` uses of a ModuleContext: a reset is a stop, which makes the
    lines sent before it void where they would start (as the dispatcher does with tickets)."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.stops = 0
        self.core = SimpleNamespace(protocol=SimpleNamespace(line_limit=256))
        self.control = SimpleNamespace(**{name: (lambda n=name: self._control(n))
                                          for name in ("hold", "resume", "reset",
                                                       "emergency_stop")})
        self.gate = asyncio.Event()

    def _control(self, name: str) -> None:
        self.calls.append(name)
        self.stops += name in ("reset", "emergency_stop")

    def ticket(self) -> int:
        return self.stops

    async def run_gcode(self, text: str, ticket: int | None = None) -> list[str]:
        if ticket is not None and ticket != self.stops:
            raise CommandError(Error.BUSY, "a stop came after this line was sent: not run")
        self.calls.append(text)
        await self.gate.wait()
        if text == "G999":
            raise CommandError(Error.UNSUPPORTED, "unsupported")
        return []

    async def start_job(self, name: str, ticket: int | None = None) -> None:
        raise CommandError(Error.FILE_ERROR, f"no job file {name}")


async def test_control_answers_each_line_once_and_a_reset_drops_what_has_not_started() -> None:
    ctx, replies = FakeContext(), []
    control = Control(ctx, replies.append, allowed=True, max_lines=10,  # type: ignore[arg-type]
                      max_payload_bytes=1000)
    task = asyncio.create_task(control.run())
    control.on_command("gcode", b'{"id": "a", "lines": ["G0 X1", "G999"]}')
    control.on_command("gcode", b'{"id": "b", "lines": ["G0 X2"]}')
    await asyncio.sleep(0)
    ctx.gate.set()
    await asyncio.sleep(0.01)
    control.on_command("job", b'{"id": "j", "name": "x.nc"}')
    ctx.gate.clear()
    control.on_command("gcode", b'{"id": "c", "lines": ["G0 X3", "G0 X4"]}')
    await asyncio.sleep(0)
    control.on_command("realtime", b"reset")  # "G0 X3" is running; "G0 X4" is dropped
    ctx.gate.set()
    await asyncio.sleep(0.01)
    task.cancel()
    gcode = [(r["id"], r["index"], r["ok"]) for r in replies if r["command"] == "gcode"]
    assert gcode == [("a", 0, True), ("a", 1, False), ("b", 0, True), ("c", 0, True),
                     ("c", 1, False)]
    assert replies[-1]["error"] == {
        "reason": "refused", "code": 45,
        "message": "error:45 a stop came after this line was sent: not run"}
    job = next(r for r in replies if r["command"] == "job")
    assert job["error"]["code"] == 44 and job["error"]["reason"] == "refused"
    assert ctx.calls == ["G0 X1", "G999", "G0 X2", "G0 X3", "reset"]


async def test_an_m112_line_stops_the_machine_on_arrival_ahead_of_waiting_lines() -> None:
    ctx, replies = FakeContext(), []
    control = Control(ctx, replies.append, allowed=True, max_lines=10,  # type: ignore[arg-type]
                      max_payload_bytes=1000)
    task = asyncio.create_task(control.run())
    control.on_command("gcode", b'{"id": "a", "lines": ["G0 X1"]}')
    await asyncio.sleep(0)  # "G0 X1" waits for planner room
    control.on_command("gcode", b'{"id": "b", "lines": ["G0 X2", "m 112"]}')
    assert ctx.calls == ["G0 X1", "emergency_stop"]
    task.cancel()


def test_control_disabled_refuses_everything_and_keeps_the_id() -> None:
    ctx, replies = FakeContext(), []
    control = Control(ctx, replies.append, allowed=False, max_lines=10,  # type: ignore[arg-type]
                      max_payload_bytes=1000)
    control.on_command("gcode", b'{"id": "a", "lines": ["G0 X1"]}')
    control.on_command("realtime", b"hold")
    control.on_command("gcode", b"x" * 5000)
    assert [r["id"] for r in replies] == ["a", None, None]
    assert all(r["error"]["reason"] == "control_disabled" for r in replies)
    assert ctx.calls == [] and control.refused == 3


def test_check_config_names_the_file_section_and_key(
    tmp_path: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    from server.cli import main

    bad = tmp_path / "fleet.toml"
    bad.write_text((REPO / "examples" / "mqtt.toml").read_text().replace(
        'url = "mqtt://broker.local:1883"', 'url = "tcp://broker.local:1883"').replace(
        "qos = 1", "qos = 3"))
    assert main(["check-config", str(bad)]) == 1
    errors = capsys.readouterr().err
    assert f"{bad}: [mqtt] url: the scheme must be mqtt:// or mqtts://" in errors
    assert f"{bad}: [mqtt] qos: Input should be less than or equal to 2" in errors


async def test_a_retained_command_is_refused_once_and_never_run() -> None:
    ctx, replies = FakeContext(), []
    control = Control(ctx, replies.append, allowed=True, max_lines=10,  # type: ignore[arg-type]
                      max_payload_bytes=1000)
    task = asyncio.create_task(control.run())
    ctx.gate.set()
    stored = b'{"id": "s", "lines": ["G0 X123 Y45"]}'
    for _ in range(3):  # the broker sends it again after each reconnect
        control.on_command("gcode", stored, retained=True)
    control.on_command("realtime", b"reset", retained=True)
    control.on_command("gcode", b"", retained=True)  # clearing the stored message
    control.on_command("gcode", b'{"id": "p", "lines": ["G0 X5"]}')
    await asyncio.sleep(0.01)
    task.cancel()
    assert [(r["id"], r["ok"]) for r in replies] == [("s", False), (None, False), ("p", True)]
    assert replies[0]["error"]["reason"] == "retained"
    assert "retain flag" in replies[0]["error"]["message"]
    assert ctx.calls == ["G0 X5"]


class SamplingContext:
    """What the status sampler of ``[mqtt]`` uses of its module context: the machine's status
    (``state`` set by the test) and the events that wake it."""

    def __init__(self) -> None:
        self.core = SimpleNamespace(machine=SimpleNamespace(name="m"))
        self.state = "Idle"
        self.wakers: list[Any] = []

    def subscribe(self, event: Any, handler: Any) -> None:
        self.wakers.append(handler)

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "moving": self.state == "Run"}

    def emit(self) -> None:
        for handler in self.wakers:
            handler(None)


async def test_a_change_after_a_quiet_look_is_published_at_once_not_a_period_later(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The fleet's staleness: a look that found nothing new (the idle machine's look every
    ``IDLE_LOOK_S``) left the sampler deaf for a whole period, so a change right after it
    waited up to a period to be published, and the next one a period more (fifty machines:
    worst 1.08 s at ``status_hz`` 2). Only a publication starts a period."""
    import modules.mqtt.module as module

    monkeypatch.setattr(module, "IDLE_LOOK_S", 1.5)
    ctx = SamplingContext()
    published, task = sampling(ctx, status_hz=1)
    loop = asyncio.get_running_loop()
    await asyncio.sleep(1.8)  # the Idle published at once; a quiet look at 1.5 s
    ctx.state = "Alarm"
    changed_s = loop.time()
    ctx.emit()
    await asyncio.sleep(0.6)
    task.cancel()
    assert [state for _, state in published] == ["Idle", "Alarm"]
    assert published[1][0] - changed_s < 0.3  # the old sampler: 0.7 s (deaf until 2.5 s)


def sampling(ctx: SamplingContext, status_hz: float) -> tuple[list[tuple[float, str]],
                                                             asyncio.Task[None]]:
    """The ``[mqtt]`` module's status sampler running on ``ctx``: what it publishes (the
    event loop's time, the state), and its task."""
    import modules.mqtt.module as module

    mqtt = module.Mqtt(ctx, module.MqttConfig(url="mqtt://x", status_hz=status_hz))  # type: ignore[arg-type]
    loop = asyncio.get_running_loop()
    published: list[tuple[float, str]] = []
    mqtt.outbox.put_status = lambda message: published.append(  # type: ignore[method-assign]
        (loop.time(), json.loads(message.payload)["state"]))
    return published, asyncio.create_task(mqtt._sample())


async def test_the_end_of_a_move_is_published_at_once_not_a_period_after_its_start() -> None:
    """A short move (a G0 through the broker): its Run was published, and its Idle waited a
    whole period behind it (``status_hz`` 2: 0.5 s, most of the fleet's staleness). A change
    of state now waits only ``STATE_GAP_S``; other changes still wait their period."""
    ctx = SamplingContext()
    published, task = sampling(ctx, status_hz=1)
    loop = asyncio.get_running_loop()
    await asyncio.sleep(1.1)  # Idle published, a period ago
    ctx.state = "Run"
    ctx.emit()
    await asyncio.sleep(0.05)
    ctx.state = "Idle"
    stopped_s = loop.time()
    ctx.emit()
    await asyncio.sleep(0.4)
    task.cancel()
    assert [state for _, state in published] == ["Idle", "Run", "Idle"]
    assert published[2][0] - stopped_s < 0.3  # the old sampler: 0.95 s (a period after Run)
