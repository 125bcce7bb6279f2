"""``motiond check-config``'s account of a config: the merged machine, each value with where it
came from (the file, the built-in machine, or the option's own default), and who controls
without the token."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from server.config import Config, client_networks

MODEL_DEFAULT = "default"
SECRETS = frozenset({"token", "password"})  # shown as set, never printed


def describe(config: Config, layers: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """TOML-like lines: ``[section]`` then ``key = value  # origin``, unset options left out."""
    tables: dict[str, Any] = config.core.model_dump(mode="json")
    for spec in config.modules:
        tables[spec.section] = spec.config.model_dump(mode="json")
    lines: list[str] = []
    for section, body in tables.items():
        _table(lines, (section,), body, layers)
    return lines


def trusted(config: Config) -> str:
    """Who controls without the token (``[protocol] trusted_clients``), in one line."""
    networks = client_networks(config.core.protocol.trusted_clients)
    if not networks:
        return "trusted clients: none (every sender logs in with $AUTH when a token is set)"
    return "trusted clients (control without the token): " + ", ".join(
        f"{net} ({net.num_addresses} address{'es' if net.num_addresses > 1 else ''})"
        for net in networks)


def _table(lines: list[str], path: tuple[str, ...], body: Mapping[str, Any],
           layers: list[tuple[str, dict[str, Any]]]) -> None:
    scalars = {key: value for key, value in body.items()
               if not isinstance(value, dict) and value is not None}
    if scalars:
        lines.append(f"[{'.'.join(path)}]")
    for key, value in scalars.items():
        shown = '"<set>"' if key in SECRETS else json.dumps(value)
        lines.append(f"{key} = {shown}  # {_origin((*path, key), layers)}")
    for key, value in body.items():
        if isinstance(value, dict):
            _table(lines, (*path, key), value, layers)


def _origin(path: tuple[str, ...], layers: list[tuple[str, dict[str, Any]]]) -> str:
    """The label of the last layer that names ``path`` (a section like ``switch.air`` is two
    levels in the file's tables), else the option's own default."""
    keys = [part for name in path for part in name.split(".")]
    for label, data in reversed(layers):
        node: Any = data
        for key in keys:
            if not isinstance(node, dict) or key not in node:
                break
            node = node[key]
        else:
            return str(label)
    return MODEL_DEFAULT
