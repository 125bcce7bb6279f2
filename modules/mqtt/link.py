"""The broker connection: connect, greet, send and receive; on any failure reconnect with a
capped exponential back-off. Nothing here ever raises for a broker that is down or goes away.

One connection at a time: on connect it publishes ``online`` (retained; the last will says
``offline``), the greeting messages (Home Assistant discovery) and the current status, then
subscribes to the command topics and runs a sender (draining the :class:`Outbox`) beside a
receiver (handing each message, with its retain flag, to ``on_message``, a plain function that
never waits). When cancelled (shutdown), it publishes ``offline`` before it disconnects.

Retained commands: with MQTT 5 (the default) the command topics are subscribed with retain
handling 2 (the broker sends no stored message when subscribing) and retain-as-published (a
message published with the retain flag arrives with it), so the receiver can refuse it; with
MQTT 3.1.1 the broker sends stored messages with the flag set on each (re)subscription.

Connecting, publishing, subscribing and disconnecting are each bounded by ``asyncio.timeout``
around aiomqtt calls made without a timeout of their own (``math.inf``): aiomqtt's timeouts use
``asyncio.wait_for``, which on Python 3.11 loses a cancellation that arrives with the awaited
reply, and a sender that misses its cancellation keeps the module (and so the server's
shutdown) alive.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import random
import ssl
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import aiomqtt
from paho.mqtt.subscribeoptions import SubscribeOptions

from modules.mqtt.config import BrokerAddress, Topics
from modules.mqtt.outbox import Outbox, Outgoing

INCOMING_LIMIT = 1000  # messages received and not yet handled; more are dropped (and counted)
PUBLISH_TIMEOUT_S = 10.0
CONNECT_TIMEOUT_S = 15.0
CLOSE_TIMEOUT_S = 2.0
FAREWELL_TIMEOUT_S = 0.5
FIRST_DELAY_S = 0.5
NOT_CONNECTED = (aiomqtt.MqttError, OSError, TimeoutError)


@dataclass(frozen=True, slots=True)
class Login:
    """What a connection attempt needs from files: the password and the TLS context."""

    username: str | None
    password: str | None
    tls: ssl.SSLContext | None


class _CountDrops(logging.Filter):
    """aiomqtt logs one warning per incoming message dropped from its full queue: count them
    instead (a flood would fill the log)."""

    def __init__(self) -> None:
        super().__init__()
        self.dropped = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if "queue is full" in record.getMessage():
            self.dropped += 1
            return False
        return True


class Link:
    """Owns the connection to one broker for one machine."""

    def __init__(
        self, broker: BrokerAddress, topics: Topics, outbox: Outbox, *, client_id: str,
        qos: int, keepalive_s: int, reconnect_max_s: float, log: logging.Logger,
        mqtt5: bool = True,
    ) -> None:
        self.broker, self.topics, self.outbox = broker, topics, outbox
        self.client_id, self.qos, self.keepalive_s = client_id, qos, keepalive_s
        self.reconnect_max_s = reconnect_max_s
        self.log = log
        self.connected = False
        self.connections = 0  # successful connections so far
        self.greeting: Callable[[], list[Outgoing]] = list
        self.on_message: Callable[[str, bytes, bool], None] = lambda topic, data, retained: None
        self.mqtt5 = mqtt5
        self._drops = _CountDrops()
        self._client_log = log.getChild("client")
        self._client_log.addFilter(self._drops)

    @property
    def dropped_incoming(self) -> int:
        return self._drops.dropped

    async def run(self, login: Callable[[], Login]) -> None:
        """Stay connected until cancelled. ``login`` runs in a thread before each attempt (it
        reads files: a password file or CA certificates that cannot be read are retried)."""
        delay_s, quiet = FIRST_DELAY_S, False
        while True:
            connections = self.connections
            try:
                await self._session(await asyncio.to_thread(login))
            except* NOT_CONNECTED as group:
                if self.connections > connections:  # it was up: start the back-off again
                    delay_s, quiet = FIRST_DELAY_S, False
                    self.log.warning("lost broker %s: %s; reconnecting", self.broker,
                                     _reason(group))
                elif not quiet:
                    quiet = True
                    self.log.warning("cannot reach broker %s: %s; retrying (back-off up to "
                                     "%.0f s)", self.broker, _reason(group), self.reconnect_max_s)
                else:
                    self.log.debug("broker %s: %s", self.broker, _reason(group))
            await asyncio.sleep(delay_s * random.uniform(0.8, 1.2))
            delay_s = min(self.reconnect_max_s, delay_s * 2)

    async def _session(self, login: Login) -> None:
        client = aiomqtt.Client(
            self.broker.host, self.broker.port, username=login.username,
            password=login.password, identifier=self.client_id, tls_context=login.tls,
            will=aiomqtt.Will(self.topics.availability, b"offline", self.qos, retain=True),
            keepalive=self.keepalive_s, timeout=math.inf, logger=self._client_log,
            max_queued_incoming_messages=INCOMING_LIMIT,
            **_session_options(self.mqtt5),
        )
        async with asyncio.timeout(CONNECT_TIMEOUT_S):
            await client.__aenter__()
        try:
            await self._connected(client)
        finally:
            with contextlib.suppress(*NOT_CONNECTED):
                async with asyncio.timeout(CLOSE_TIMEOUT_S):
                    await client.__aexit__(None, None, None)

    async def _connected(self, client: aiomqtt.Client) -> None:
        self.connected = True
        self.connections += 1
        self.log.info("connected to %s as %s", self.broker, self.client_id)
        try:
            await self._greet(client)
            async with asyncio.TaskGroup() as group:
                group.create_task(self._send(client))
                group.create_task(self._receive(client))
        except asyncio.CancelledError:
            await self._farewell(client)
            raise
        finally:
            self.connected = False

    async def _publish(self, client: aiomqtt.Client, message: Outgoing,
                       timeout_s: float = PUBLISH_TIMEOUT_S) -> None:
        async with asyncio.timeout(timeout_s):
            await client.publish(message.topic, message.payload, self.qos, message.retain,
                                 timeout=math.inf)

    async def _greet(self, client: aiomqtt.Client) -> None:
        await self._publish(client, Outgoing(self.topics.availability, b"online", True))
        for message in self.greeting():
            await self._publish(client, message)
        async with asyncio.timeout(PUBLISH_TIMEOUT_S):
            options = _command_options(self.qos, self.mqtt5)  # carries the QoS, if any
            granted = await client.subscribe(
                self.topics.commands, self.qos if options is None else 0, options=options,
                timeout=math.inf)
        if any(_refused(code) for code in granted):
            self.log.warning("the broker refused %s to this user (its ACL): commands cannot "
                             "be received or answered", self.topics.commands)

    async def _send(self, client: aiomqtt.Client) -> None:
        while True:
            message = await self.outbox.get()
            try:
                await self._publish(client, message)
            except NOT_CONNECTED:
                if message.topic == self.topics.status:
                    self.outbox.restore_status(message)
                raise

    async def _receive(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            payload = message.payload
            if isinstance(payload, str):
                data = payload.encode()
            elif isinstance(payload, bytes | bytearray):
                data = bytes(payload)
            else:
                data = b"" if payload is None else str(payload).encode()
            self.on_message(str(message.topic), data, bool(message.retain))

    async def _farewell(self, client: aiomqtt.Client) -> None:
        """Shutdown: say ``offline`` (the will is only for a connection that breaks)."""
        with contextlib.suppress(*NOT_CONNECTED):
            offline = Outgoing(self.topics.availability, b"offline", True)
            await self._publish(client, offline, FAREWELL_TIMEOUT_S)


def _session_options(mqtt5: bool) -> dict[str, Any]:
    """A clean session on every connection, in either protocol version's terms."""
    if mqtt5:
        return {"protocol": aiomqtt.ProtocolVersion.V5, "clean_start": True}
    return {"protocol": aiomqtt.ProtocolVersion.V311, "clean_session": True}


def _command_options(qos: int, mqtt5: bool) -> SubscribeOptions | None:
    """MQTT 5: no stored (retained) message on subscribing; the retain flag as published."""
    if not mqtt5:
        return None
    return SubscribeOptions(qos=qos, retainAsPublished=True,
                            retainHandling=SubscribeOptions.RETAIN_DO_NOT_SEND)


def _refused(code: object) -> bool:
    """A SUBACK return code of 128 or more is a refusal (MQTT 3.1.1 and 5)."""
    value = getattr(code, "value", code)
    return isinstance(value, int) and value >= 0x80


def _reason(group: BaseExceptionGroup[BaseException]) -> str:
    errors = group.exceptions
    return "; ".join(str(error) or type(error).__name__ for error in errors[:3])
