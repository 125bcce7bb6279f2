"""Transports: thin adapters that move bytes between clients and sessions."""

from __future__ import annotations

from server.app import TransportFactory
from server.config import Config


def default_transports(config: Config) -> list[TransportFactory]:
    """The transports the config enables, in start order."""
    import server.api  # noqa: F401 - registers the JSON API's routes on HttpTransport
    from server.transports.serial import SerialTransport
    from server.transports.tcp import TcpTransport
    from server.transports.websocket import HttpTransport

    core = config.core
    factories: list[TransportFactory] = []
    if core.tcp.enabled:
        factories.append(TcpTransport)
    if core.http.enabled:
        factories.append(HttpTransport)
    if core.serial.device or core.serial.pty:
        factories.append(SerialTransport)
    return factories
