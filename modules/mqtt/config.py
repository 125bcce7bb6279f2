"""``[mqtt]`` options, the broker address and the topic names (pure: no I/O)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal
from urllib.parse import urlsplit

from pydantic import Field, FilePath, field_validator, model_validator

from server.kernel.module import ModuleConfig

SCHEMES = {"mqtt": (1883, False), "mqtts": (8883, True)}
_NOT_SLUG = re.compile(r"[^a-z0-9]+")


@dataclass(frozen=True, slots=True)
class BrokerAddress:
    """Where the broker listens; ``tls`` for ``mqtts://``."""

    host: str
    port: int
    tls: bool

    def __str__(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def broker_address(url: str) -> BrokerAddress:
    """Parse ``mqtt://host[:port]`` or ``mqtts://host[:port]``; ValueError says what is wrong."""
    parts = urlsplit(url.strip())
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise ValueError(f"the scheme must be mqtt:// or mqtts:// (TLS), not {url!r}")
    if parts.username is not None or parts.password is not None:
        raise ValueError("put credentials in username/password or password_file, not in the url")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        raise ValueError("the url is mqtt://host[:port], without a path or query")
    try:
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"invalid port in {url!r}") from exc
    if not parts.hostname:
        raise ValueError(f"no host in {url!r}")
    default_port, tls = SCHEMES[scheme]
    return BrokerAddress(parts.hostname, port or default_port, tls)


def slug(name: str) -> str:
    """A machine name as one topic level and Home Assistant id: ``Laser #2`` -> ``laser-2``."""
    return _NOT_SLUG.sub("-", name.lower()).strip("-") or "motiond"


def check_topic_prefix(prefix: str) -> str:
    """A publish topic prefix: levels without wildcards, not empty, not starting with ``$``."""
    if not prefix or prefix.startswith("$") or any(c in prefix for c in "+#\0"):
        raise ValueError("a topic prefix has no +, # or NUL and does not start with $")
    if any(not level for level in prefix.split("/")):
        raise ValueError(f"empty topic level in {prefix!r} (a leading, trailing or double /)")
    return prefix


class MqttConfig(ModuleConfig):
    """``[mqtt]``: publish this machine on an MQTT broker (and take commands, if allowed)."""

    url: str = Field(description="broker: mqtt://host[:1883] or mqtts://host[:8883] (TLS)")
    username: str | None = Field(None, min_length=1, description="broker user")
    password: str | None = Field(None, min_length=1, description="broker password")
    password_file: FilePath | None = Field(
        None, description="file holding the broker password (first line), instead of password")
    ca_file: FilePath | None = Field(
        None, description="mqtts: CA certificates to trust (default: the system's)")
    client_id: str | None = Field(
        None, min_length=1, max_length=128, description="default: motiond-<machine slug>")
    topic_prefix: str | None = Field(
        None, max_length=200, description="default: motiond/<machine slug>")
    qos: int = Field(1, ge=0, le=2, description="QoS of everything published and subscribed")
    allow_control: bool = Field(
        False, description="obey <prefix>/cmd/...; the broker's ACLs decide who may publish")
    status_hz: float = Field(2.0, gt=0, le=50, description="most status publications a second")
    keepalive_s: int = Field(
        15, ge=5, le=3600, description="MQTT keep-alive: the broker reports offline within ~1.5x")
    homeassistant: bool = Field(True, description="publish Home Assistant discovery configs")
    discovery_prefix: str = Field("homeassistant", min_length=1, max_length=100)
    max_lines_per_message: int = Field(100, ge=1, le=10_000, description="cmd/gcode lines")
    max_payload_bytes: int = Field(64 << 10, ge=256, le=16 << 20, description="cmd payloads")
    pending_messages: int = Field(
        1000, ge=16, le=100_000,
        description="replies and events held while the broker is slow or away (oldest dropped)")
    reconnect_max_s: float = Field(30.0, ge=0.5, le=3600, description="cap of the back-off")
    protocol: Literal["5", "3.1.1"] = Field(
        "5", description="MQTT version: 5 keeps retained commands from being sent at all; "
        "3.1.1 for brokers without it (retained commands are then refused as they arrive)")

    @field_validator("url")
    @classmethod
    def _url(cls, url: str) -> str:
        broker_address(url)
        return url

    @field_validator("topic_prefix", "discovery_prefix")
    @classmethod
    def _prefix(cls, prefix: str | None) -> str | None:
        return None if prefix is None else check_topic_prefix(prefix)

    @model_validator(mode="after")
    def _credentials(self) -> MqttConfig:
        if self.password is not None and self.password_file is not None:
            raise ValueError("give password or password_file, not both")
        if (self.password or self.password_file) and self.username is None:
            raise ValueError("a password needs a username")
        if self.ca_file is not None and not broker_address(self.url).tls:
            raise ValueError("ca_file needs an mqtts:// url")
        return self


@dataclass(frozen=True, slots=True)
class Topics:
    """Every topic of one machine, under its prefix."""

    prefix: str

    @property
    def availability(self) -> str:
        return f"{self.prefix}/availability"

    @property
    def status(self) -> str:
        return f"{self.prefix}/status"

    @property
    def reply(self) -> str:
        return f"{self.prefix}/reply"

    @property
    def commands(self) -> str:
        """The filter the module subscribes to: ``<prefix>/cmd/+``."""
        return f"{self.prefix}/cmd/+"

    def command(self, name: str) -> str:
        return f"{self.prefix}/cmd/{name}"

    def event(self, name: str) -> str:
        return f"{self.prefix}/event/{name}"

    def command_of(self, topic: str) -> str | None:
        """``gcode`` for ``<prefix>/cmd/gcode``; None for a topic outside ``<prefix>/cmd/``."""
        head = f"{self.prefix}/cmd/"
        return topic[len(head):] if topic.startswith(head) else None
