"""A real Mosquitto broker for the MQTT tests, and a small client to watch and command it.

The broker listens on a free loopback port with a generated config (persistence off, so a
restart forgets every retained message: whatever is retained afterwards was published again).
With ``users`` it takes only those users (a password file made with ``mosquitto_passwd``);
with ``tls`` it speaks only TLS, with a self-signed certificate for 127.0.0.1 (``openssl``)
saved as ``cert.pem`` in its folder.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import aiomqtt

from tests.support.processes import free_port


def mosquitto_binary() -> str:
    found = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not os.access(found, os.X_OK):
        raise RuntimeError("mosquitto is not installed (apt-get install mosquitto)")
    return found


@dataclass
class Broker:
    """A running ``mosquitto`` on ``127.0.0.1:port``."""

    folder: Path
    port: int
    process: asyncio.subprocess.Process | None = None

    tls: bool = False

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://127.0.0.1:{self.port}"

    async def start(self) -> None:
        self.process = await asyncio.create_subprocess_exec(
            mosquitto_binary(), "-c", str(self.folder / "mosquitto.conf"),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
        for _ in range(200):
            if self.process.returncode is not None:
                raise RuntimeError(f"mosquitto exited with {self.process.returncode}")
            with contextlib.suppress(OSError):
                _, writer = await asyncio.open_connection("127.0.0.1", self.port)
                writer.close()
                return
            await asyncio.sleep(0.025)
        raise TimeoutError("mosquitto did not listen")

    async def stop(self) -> None:
        process, self.process = self.process, None
        if process is not None and process.returncode is None:
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), 5)
            except TimeoutError:
                process.kill()
                await process.wait()


@contextlib.asynccontextmanager
async def mosquitto(
    folder: Path, users: dict[str, str] | None = None, tls: bool = False
) -> AsyncIterator[Broker]:
    folder.mkdir(parents=True, exist_ok=True)
    broker = Broker(folder, free_port(), tls=tls)
    lines = [f"listener {broker.port} 127.0.0.1", "persistence false", "user root",
             "log_dest none", "max_queued_messages 100000"]
    if tls:
        await self_signed(folder / "cert.pem", folder / "key.pem")
        lines += [f"certfile {folder / 'cert.pem'}", f"keyfile {folder / 'key.pem'}"]
    if users:
        passwords = folder / "passwords"
        for number, (user, password) in enumerate(users.items()):
            create = ["-c"] if number == 0 else []
            made = await asyncio.create_subprocess_exec(
                "mosquitto_passwd", *create, "-b", str(passwords), user, password)
            assert await made.wait() == 0, "mosquitto_passwd failed"
        lines += ["allow_anonymous false", f"password_file {passwords}"]
    else:
        lines.append("allow_anonymous true")
    (folder / "mosquitto.conf").write_text("\n".join(lines) + "\n")
    await broker.start()
    try:
        yield broker
    finally:
        await broker.stop()


async def self_signed(cert: Path, key: Path) -> None:
    """A certificate for 127.0.0.1, its own CA (valid one day)."""
    made = await asyncio.create_subprocess_exec(
        "openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
        "-keyout", str(key), "-out", str(cert), "-subj", "/CN=127.0.0.1",
        "-addext", "subjectAltName=IP:127.0.0.1",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
    assert await made.wait() == 0, "openssl could not make a certificate"


@dataclass
class Watcher:
    """A client subscribed to some topics, keeping every message (topic, payload)."""

    client: aiomqtt.Client
    messages: list[tuple[str, bytes]] = field(default_factory=list)
    arrived: asyncio.Event = field(default_factory=asyncio.Event)

    async def publish(self, topic: str, payload: Any, qos: int = 1) -> None:
        data = payload if isinstance(payload, bytes | str) else json.dumps(payload)
        await self.client.publish(topic, data, qos)

    async def wait_for(
        self, topic: str, predicate: Callable[[bytes], bool] = lambda payload: True,
        timeout_s: float = 10.0,
    ) -> bytes:
        """The first message on ``topic`` (seen already or coming) that matches."""
        async with asyncio.timeout(timeout_s):
            seen = 0
            while True:
                for got_topic, payload in self.messages[seen:]:
                    if got_topic == topic and predicate(payload):
                        return payload
                seen = len(self.messages)
                self.arrived.clear()
                await self.arrived.wait()

    async def wait_json(
        self, topic: str, predicate: Callable[[Any], bool] = lambda data: True,
        timeout_s: float = 10.0,
    ) -> Any:
        payload = await self.wait_for(topic, lambda p: _matches(p, predicate), timeout_s)
        return json.loads(payload)

    def on(self, topic: str) -> list[bytes]:
        return [payload for got, payload in self.messages if got == topic]

    def json_on(self, topic: str) -> list[Any]:
        return [json.loads(payload) for payload in self.on(topic)]


def _matches(payload: bytes, predicate: Callable[[Any], bool]) -> bool:
    try:
        return bool(predicate(json.loads(payload)))
    except (ValueError, KeyError, TypeError):
        return False


@contextlib.asynccontextmanager
async def watching(broker: Broker, *topics: str, **login: Any) -> AsyncIterator[Watcher]:
    """A client on ``broker`` subscribed to ``topics`` (wildcards allowed)."""
    client = aiomqtt.Client("127.0.0.1", broker.port, **login)
    async with client:
        watcher = Watcher(client)
        for topic in topics:
            await client.subscribe(topic, 1)

        async def read() -> None:
            async for message in client.messages:
                payload = message.payload
                data = payload if isinstance(payload, bytes) else str(payload).encode()
                watcher.messages.append((str(message.topic), data))
                watcher.arrived.set()

        reader = asyncio.create_task(read())
        try:
            yield watcher
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await reader


def mqtt_toml(broker: Broker, **options: Any) -> str:
    """A ``[mqtt]`` section for ``broker`` (booleans, numbers and strings in ``options``)."""
    lines = ["[mqtt]", f'url = "{broker.url}"']
    for key, value in options.items():
        lines.append(f"{key} = {json.dumps(value)}")
    return "\n".join(lines) + "\n"
