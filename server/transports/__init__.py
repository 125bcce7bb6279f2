"""Transports: thin adapters that move bytes between clients and sessions."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.app import TransportFactory
    from server.config import Config


def default_transports(config: Config) -> list[TransportFactory]:
    """The transports the config enables, in start order."""
    from server.api.server import http_with_api
    from server.transports.serial import SerialTransport
    from server.transports.tcp import TcpTransport

    core = config.core
    factories: list[TransportFactory] = []
    if core.tcp.enabled:
        factories.append(TcpTransport)
    if core.http.enabled:
        factories.append(http_with_api)
    if core.serial.device or core.serial.pty:
        factories.append(SerialTransport)
    return factories
