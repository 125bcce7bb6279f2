"""``[mqtt]``: this machine on an MQTT broker, for dashboards, fleets and home automation.

    [mqtt]
    url = "mqtt://broker.local:1883"
    username = "laser-1"
    password_file = "/etc/motiond/mqtt-password"
    allow_control = false

Topics, under ``topic_prefix`` (default ``motiond/<machine slug>``):

- ``availability``: ``online`` (retained), and ``offline`` as the last will and at shutdown;
- ``status``: retained JSON (:func:`~modules.mqtt.payloads.status_payload`), published when it
  changes, at most ``status_hz`` times a second;
- ``event/alarm``, ``event/job``: an alarm (code, message, meaning); a job's ``start``,
  ``pause``, ``resume`` and ``end`` (done, failed or aborted);
- ``cmd/...`` and ``reply``: see :mod:`modules.mqtt.control` (a retained command is never
  executed); replies and events are never retained;
- Home Assistant discovery under ``discovery_prefix`` (:mod:`modules.mqtt.discovery`).

The broker never slows the machine: samples and events go to a bounded :class:`Outbox` that
one sender drains; the connection (:mod:`modules.mqtt.link`) reconnects with back-off and
publishes the retained state again. ``aiomqtt`` is needed (``pip install 'motiond[mqtt]'``);
it is imported when the module starts, so configs without ``[mqtt]`` never need it.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import math
import ssl
from pathlib import Path
from typing import TYPE_CHECKING, Any

from modules.mqtt.config import MqttConfig, Topics, broker_address, slug
from modules.mqtt.control import Control
from modules.mqtt.discovery import Device, discovery_messages
from modules.mqtt.outbox import Outbox, Outgoing
from modules.mqtt.payloads import encode, status_payload
from server import __version__
from server.errors import ConfigError
from server.kernel.module import Module, ModuleContext
from server.runtime.events import Event, MachineState

if TYPE_CHECKING:
    from modules.mqtt.link import Link, Login

IDLE_LOOK_S = 1.0  # while nothing signals a change, the status is still sampled this often
_WAKE_EVENTS = (Event.STATE, Event.HALT, Event.CLEAR_HALT, Event.HOLD, Event.HOLD_STOPPED,
                Event.RESUME, Event.OVERRIDE, Event.ACTION, Event.PROGRAM_END, Event.JOB)
_JOB_ENDS = frozenset({"done", "failed", "aborted"})
_QUIET_STATES = frozenset({"Idle", "Alarm", "Sleep", "Check"})
STATE_GAP_S = 0.1  # a change of state is published at most this often (others: status_hz)


def _state_of(payload: dict[str, Any]) -> tuple[Any, ...]:
    """The machine's state, its alarm and its job's state (not the job's progress)."""
    job = payload.get("job")
    return payload.get("state"), payload.get("alarm"), job.get("state") if job else None


def _busy(snapshot: dict[str, Any]) -> bool:
    """Whether the machine is busy: its status will change without an event."""
    job = snapshot.get("job") or {}
    return bool(snapshot.get("moving")) or snapshot.get("state") not in _QUIET_STATES or (
        job.get("state") in ("running", "paused"))


class Mqtt(Module):
    """Publishes status, availability and events; obeys commands when allowed."""

    name = "mqtt"
    Config = MqttConfig

    def __init__(self, ctx: ModuleContext, config: MqttConfig) -> None:
        super().__init__(ctx, config)
        if importlib.util.find_spec("aiomqtt") is None:
            raise ConfigError([f"[{ctx.name}]: needs aiomqtt: pip install 'motiond[mqtt]'"])
        self.machine = ctx.core.machine.name
        self.node_id = slug(self.machine)
        self.broker = broker_address(config.url)
        self.topics = Topics(config.topic_prefix or f"motiond/{self.node_id}")
        self.client_id = config.client_id or f"motiond-{self.node_id}"
        self.outbox = Outbox(config.pending_messages)
        self.control = Control(
            ctx, self._reply, allowed=config.allow_control,
            max_lines=config.max_lines_per_message, max_payload_bytes=config.max_payload_bytes)
        self.published_status: dict[str, Any] | None = None
        self._published_s = -math.inf  # the event loop's time of the last status queued
        self._wake = asyncio.Event()
        self._job: tuple[str, float, str] | None = None  # name, started_s, state
        self.link: Link | None = None  # once running (aiomqtt is imported then)
        for event in _WAKE_EVENTS:
            ctx.subscribe(event, lambda *_: self._wake.set())
        ctx.subscribe(Event.STATE, self._on_state)
        ctx.subscribe(Event.JOB, self._on_job)

    async def run(self) -> None:
        from modules.mqtt.link import Link

        config = self.config
        link = Link(self.broker, self.topics, self.outbox, client_id=self.client_id,
                    qos=config.qos, keepalive_s=config.keepalive_s,
                    reconnect_max_s=config.reconnect_max_s, log=self.ctx.log,
                    mqtt5=config.protocol == "5")
        link.greeting = self._greeting
        link.on_message = self._on_message
        self.link = link
        async with asyncio.TaskGroup() as group:
            group.create_task(link.run(self._login), name="mqtt-link")
            group.create_task(self.control.run(), name="mqtt-gcode")
            group.create_task(self._sample(), name="mqtt-status")

    def _login(self) -> Login:
        """Run in a thread before each connection attempt: it reads files."""
        from modules.mqtt.link import Login

        config = self.config
        tls = None
        if self.broker.tls:
            tls = ssl.create_default_context(
                cafile=None if config.ca_file is None else str(config.ca_file))
        return Login(config.username, _password(config), tls)

    def status(self) -> dict[str, Any]:
        link = self.link
        return {
            "broker": str(self.broker),
            "prefix": self.topics.prefix,
            "connected": link is not None and link.connected,
            "dropped": self.outbox.dropped + (0 if link is None else link.dropped_incoming),
        }

    # -- status ---------------------------------------------------------------------------
    async def _sample(self) -> None:
        """Publish the status when it changes: a change of state (Idle, Run, Hold, Alarm, a
        job's) at most every ``STATE_GAP_S`` (so the end of a move shows at once, not a
        period after the report that it began), any other change at most ``status_hz``
        times a second. The status is looked at every period while the machine is busy (and
        after an event, at most every ``STATE_GAP_S``), at once after an event while it is
        not, and at least every ``IDLE_LOOK_S``; a change that must wait its turn is looked
        at afresh when it comes."""
        period_s = 1.0 / self.config.status_hz
        loop = asyncio.get_running_loop()
        while True:
            self._wake.clear()
            snapshot = self.ctx.status()
            payload = status_payload(snapshot, self.machine)
            due_s = self._due_s(payload, period_s)
            if due_s is not None and due_s <= loop.time():
                self._publish(payload)
                due_s = None
            if due_s is not None:
                await asyncio.sleep(due_s - loop.time())
            elif _busy(snapshot):  # (events come fast then: at most one look a STATE_GAP_S)
                await asyncio.sleep(min(period_s, STATE_GAP_S))
                await self._woken(max(0.0, period_s - STATE_GAP_S))
            else:
                await self._woken(IDLE_LOOK_S)

    def _due_s(self, payload: dict[str, Any], period_s: float) -> float | None:
        """When ``payload`` may be published (the event loop's time), or None: unchanged."""
        published = self.published_status
        if payload == published:
            return None
        state_changed = published is None or _state_of(payload) != _state_of(published)
        return self._published_s + (min(period_s, STATE_GAP_S) if state_changed else period_s)

    async def _woken(self, timeout_s: float) -> None:
        """Until an event wakes the sampler, for at most ``timeout_s``."""
        if not self._wake.is_set():
            with contextlib.suppress(TimeoutError):  # not wait_for: see modules.mqtt.link
                async with asyncio.timeout(timeout_s):
                    await self._wake.wait()

    def _publish(self, payload: dict[str, Any]) -> None:
        self.published_status = payload
        self._published_s = asyncio.get_running_loop().time()
        self.outbox.put_status(Outgoing(self.topics.status, encode(payload), retain=True))

    def _greeting(self) -> list[Outgoing]:
        """What a new connection publishes first (then the status, fresh)."""
        self._publish(status_payload(self.ctx.status(), self.machine))
        if not self.config.homeassistant:
            return []
        device = Device(self.node_id, self.machine, __version__)
        return [
            Outgoing(topic, b"" if payload is None else encode(payload), retain=True)
            for topic, payload in discovery_messages(
                self.topics, device, self.config.discovery_prefix, self.config.allow_control)
        ]

    # -- events ---------------------------------------------------------------------------
    def _on_state(self, state: MachineState) -> None:
        if state is MachineState.ALARM:
            status = self.ctx.status()
            self._event("alarm", {"alarm": status["alarm"], "state": status["state"]})

    def _on_job(self, progress: Any) -> None:
        if progress is None:
            return
        key = (progress.name, progress.started_s)
        state = str(progress.state)
        previous = self._job[2] if self._job is not None and self._job[:2] == key else None
        self._job = (*key, state)
        kind = _job_event(previous, state)
        if kind is not None:
            self._event("job", {"event": kind, "job": self.ctx.status()["job"]})

    def _event(self, name: str, payload: dict[str, Any]) -> None:
        message = {"machine": self.machine, **payload}
        self.outbox.put(Outgoing(self.topics.event(name), encode(message)))

    # -- commands -------------------------------------------------------------------------
    def _on_message(self, topic: str, payload: bytes, retained: bool = False) -> None:
        command = self.topics.command_of(topic)
        if command is not None:
            self.control.on_command(command, payload, retained=retained)

    def _reply(self, reply: dict[str, Any]) -> None:
        self.outbox.put(Outgoing(self.topics.reply, encode(reply)))


def _job_event(previous: str | None, state: str) -> str | None:
    """The event a job's change of state makes: start, pause, resume, end (or none)."""
    if state == previous:
        return None
    if state in _JOB_ENDS:
        return "end"
    if state == "paused":
        return "pause"
    if state == "running":
        return "start" if previous is None else "resume"
    return None


def _password(config: MqttConfig) -> str | None:
    if config.password_file is None:
        return config.password
    lines = Path(config.password_file).read_text().splitlines()
    return lines[0] if lines else ""
