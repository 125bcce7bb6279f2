"""Home Assistant MQTT discovery (pure): the retained ``config`` messages that make a machine
appear as one device with its state, job, progress, remaining time and an alarm sensor, and
with ``allow_control`` hold, resume and reset buttons.

See https://www.home-assistant.io/integrations/mqtt/#mqtt-discovery: a config message on
``<discovery_prefix>/<component>/<node_id>/<object_id>/config``; an empty retained payload
removes the entity (so buttons disappear when control is turned off).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from modules.mqtt.config import Topics
from modules.mqtt.payloads import REALTIME


@dataclass(frozen=True, slots=True)
class Device:
    """The machine as a Home Assistant device."""

    node_id: str  # the machine slug
    name: str
    version: str


_JOB = "value_json.job"
SENSORS: dict[str, dict[str, Any]] = {
    "state": {"name": "State", "value_template": "{{ value_json.state }}",
              "icon": "mdi:state-machine"},
    "job": {"name": "Job", "value_template": f"{{{{ {_JOB}.name if {_JOB} else 'none' }}}}",
            "icon": "mdi:file-cog-outline"},
    "progress": {"name": "Progress", "unit_of_measurement": "%", "state_class": "measurement",
                 "value_template": f"{{{{ {_JOB}.percent if {_JOB} else 0 }}}}",
                 "icon": "mdi:progress-clock"},
    "remaining": {"name": "Remaining", "unit_of_measurement": "s", "device_class": "duration",
                  "value_template": f"{{{{ ({_JOB}.remaining_s if {_JOB} else 0) or 0 }}}}"},
}


def discovery_messages(
    topics: Topics, device: Device, discovery_prefix: str, allow_control: bool
) -> list[tuple[str, dict[str, Any] | None]]:
    """``(topic, payload)`` for every entity; payload None removes it (publish empty)."""
    node = device.node_id
    messages: list[tuple[str, dict[str, Any] | None]] = []
    for key, fields in SENSORS.items():
        messages.append((f"{discovery_prefix}/sensor/{node}/{key}/config",
                         _entity(topics, device, key, state_topic=topics.status, **fields)))
    alarm = _entity(
        topics, device, "alarm", name="Alarm", device_class="problem",
        state_topic=topics.status,
        value_template="{{ 'ON' if value_json.alarm else 'OFF' }}",
        json_attributes_topic=topics.status,
        json_attributes_template="{{ (value_json.alarm or {}) | tojson }}",
    )
    messages.append((f"{discovery_prefix}/binary_sensor/{node}/alarm/config", alarm))
    for command in REALTIME:
        button = _entity(topics, device, command, name=command.capitalize(),
                         command_topic=topics.command("realtime"), payload_press=command)
        messages.append((f"{discovery_prefix}/button/{node}/{command}/config",
                         button if allow_control else None))
    return messages


def _entity(topics: Topics, device: Device, key: str, **fields: Any) -> dict[str, Any]:
    return {
        "unique_id": f"motiond_{device.node_id}_{key}",
        "availability_topic": topics.availability,
        "payload_available": "online",
        "payload_not_available": "offline",
        "device": {
            "identifiers": [f"motiond_{device.node_id}"],
            "name": device.name,
            "manufacturer": "motiond",
            "model": "motion controller",
            "sw_version": device.version,
        },
        **fields,
    }
