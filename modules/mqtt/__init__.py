"""``[mqtt]``: motiond on an MQTT broker (status, availability, events, control, Home
Assistant discovery) and ``motiond fleet``. See :mod:`modules.mqtt.module`."""

from modules.mqtt.module import Mqtt

__all__ = ["Mqtt"]
