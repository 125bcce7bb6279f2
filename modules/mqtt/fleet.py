"""``motiond fleet``: every machine on a broker, read from their retained topics.

It subscribes to ``<prefix>/+/availability`` and ``<prefix>/+/status`` for a short window
(retained messages arrive at once) and prints one row per machine: name, online or offline,
state, job and progress. Machines whose ``topic_prefix`` is not ``<prefix>/<one level>``
(the default ``motiond/<machine slug>`` is) do not show up.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from dataclasses import dataclass, field
from typing import Any

from modules.mqtt.config import broker_address, check_topic_prefix


@dataclass(slots=True)
class Machine:
    """One machine as its retained topics show it."""

    key: str  # the topic level under the prefix
    availability: str = "unknown"
    status: dict[str, Any] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        job = self.status.get("job") or {}
        return {
            "machine": str(self.status.get("machine") or self.key),
            "topic": self.key,
            "availability": self.availability,
            "state": self.status.get("state"),
            "alarm_code": (self.status.get("alarm") or {}).get("code"),
            "alarm": (self.status.get("alarm") or {}).get("meaning") or None,
            "job": job.get("name"),
            "job_state": job.get("state"),
            "progress_pct": job.get("percent"),
            "remaining_s": job.get("remaining_s"),
        }


def absorb(machines: dict[str, Machine], prefix: str, topic: str, payload: bytes) -> None:
    """Fold one retained message into ``machines`` (unknown topics and bad JSON are skipped)."""
    head = f"{prefix}/"
    if not topic.startswith(head):
        return
    key, _, leaf = topic[len(head):].partition("/")
    if not key or leaf not in ("availability", "status"):
        return
    machine = machines.setdefault(key, Machine(key))
    if leaf == "availability":
        machine.availability = payload.decode("utf-8", "replace").strip() or "unknown"
        return
    try:
        status = json.loads(payload)
    except ValueError:
        return
    if isinstance(status, dict):
        machine.status = status


def table(rows: list[dict[str, Any]]) -> str:
    """A readable table: machine, online, state, job, progress, remaining."""
    if not rows:
        return "no machines found"
    header = ("MACHINE", "ONLINE", "STATE", "JOB", "PROGRESS", "REMAINING")
    lines = [header] + [_cells(row) for row in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
        for line in lines
    )


def _cells(row: dict[str, Any]) -> tuple[str, ...]:
    progress, remaining = row["progress_pct"], row["remaining_s"]
    job = row["job"] or "-"
    if row["job_state"] and row["job_state"] != "running":
        job += f" ({row['job_state']})"
    state = row["state"] or "-"
    if row["alarm_code"]:
        state += f" {row['alarm_code']}"  # the meaning is in --json
    return (
        row["machine"], row["availability"], state, job,
        "-" if progress is None else f"{progress:.0f} %",
        "-" if remaining is None else _duration(remaining),
    )


def _duration(seconds: float) -> str:
    minutes, secs = divmod(int(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


async def collect(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Subscribe for ``args.wait_s`` seconds; the machines seen, by name."""
    import ssl

    import aiomqtt

    broker = broker_address(args.url)
    password = None
    if args.password_file is not None:
        text = await asyncio.to_thread(args.password_file.read_text)
        password = text.splitlines()[0] if text else ""
    tls = None
    if broker.tls:
        ca_file = None if args.ca_file is None else str(args.ca_file)
        tls = await asyncio.to_thread(ssl.create_default_context, cafile=ca_file)
    machines: dict[str, Machine] = {}
    client = aiomqtt.Client(broker.host, broker.port, username=args.username, password=password,
                            tls_context=tls, timeout=args.wait_s + 5)
    async with client:
        for leaf in ("availability", "status"):
            await client.subscribe(f"{args.prefix}/+/{leaf}")
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(args.wait_s):  # retained messages come at once
                async for message in client.messages:
                    payload = message.payload
                    data = payload if isinstance(payload, bytes) else str(payload or "").encode()
                    absorb(machines, args.prefix, str(message.topic), data)
    return sorted((m.row() for m in machines.values()), key=lambda row: row["machine"])


def fleet_command(args: argparse.Namespace) -> int:
    """``motiond fleet``: print the fleet; 1 if the broker cannot be reached."""
    try:
        check_topic_prefix(args.prefix)
        broker_address(args.url)
    except ValueError as exc:
        print(f"motiond fleet: {exc}", file=sys.stderr)
        return 2
    try:
        import aiomqtt
    except ImportError:
        print("motiond fleet needs aiomqtt: pip install 'motiond[mqtt]'", file=sys.stderr)
        return 2
    try:
        rows = asyncio.run(collect(args))
    except (aiomqtt.MqttError, OSError) as exc:
        print(f"motiond fleet: cannot read {args.url}: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(rows, indent=2) if args.json else table(rows))
    return 0
