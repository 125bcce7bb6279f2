"""A fleet on one broker: N ``motiond`` processes (simulated machines, ``[mqtt]``) on one
Mosquitto here, each publishing its status and Home Assistant discovery.

* start: until every machine is online on the broker (started in waves of :data:`WAVE`);
* idle: each instance's CPU (% of a core) and memory (RSS), and the broker's, over
  :data:`IDLE_S` seconds;
* discovery: Home Assistant configs retained per machine;
* staleness: a short move is commanded to every machine through the broker
  (``cmd/gcode``), :data:`SPACING_S` apart, then to all at once; for each, the time from
  its command until the fleet's view (a client subscribed to ``motiond/+/status``) shows
  it idle at its new position (goal: every machine's state within 1 s);
* ``motiond fleet --json``: every machine listed online;
* a job sent to one machine through the broker (``cmd/job``) runs to its end.

Run: ``python -m benchmarks fleet [--quick] [--machines N]`` (default 50; quick: 10).
Bounded: each wave of starts and each wait has a timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.common import BenchResult, standalone
from tests.support.broker import Broker, Watcher, mosquitto, mqtt_toml, watching
from tests.support.processes import REPO, Served, motiond

MACHINES = 50
QUICK_MACHINES = 10
WAVE = 5  # machines started at once (each start is a second or two of CPU here)
START_TIMEOUT_S = 120.0  # per wave
IDLE_S = 5.0
STALE_GOAL_S = 1.0
POLL_S = 0.01  # the staleness run looks at the view's new messages this often
SPACING_S = 0.05  # between the commands of the staleness run (machines change one by one)
JOB = "G21 G90\nG1 X20 F1200\nG1 Y20\nG1 X0\nG1 Y0\n"  # 4 s of motion
CLOCK_TICKS_S = os.sysconf("SC_CLK_TCK")
PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")


def slug(index: int) -> str:
    return f"m{index:02d}"


def usage(pid: int) -> tuple[float, int]:
    """CPU seconds so far and resident bytes of process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_S, int(fields[21]) * PAGE_BYTES


@dataclass
class Fleet:
    """The broker, the machines and a client watching them all (the fleet's view)."""

    broker: Broker
    servers: list[Served]
    view: Watcher
    started_s: float
    figures: dict[str, Any] = field(default_factory=dict)


@contextlib.asynccontextmanager
async def fleet(folder: Path, count: int) -> AsyncIterator[Fleet]:
    """``count`` machines ``m00``.. on one broker, all online, watched."""
    async with (mosquitto(folder / "broker") as broker, contextlib.AsyncExitStack() as stack,
                watching(broker, "motiond/+/availability", "motiond/+/status",
                         "motiond/+/reply", "motiond/+/event/+", "homeassistant/#") as view):
        began_s = time.perf_counter()
        servers: list[Served] = []
        for first in range(0, count, WAVE):
            wave = [start_machine(stack, folder, broker, index)
                    for index in range(first, min(count, first + WAVE))]
            servers += await asyncio.wait_for(asyncio.gather(*wave), START_TIMEOUT_S)
        for index in range(count):
            await view.wait_for(f"motiond/{slug(index)}/availability",
                                lambda p: p == b"online", timeout_s=START_TIMEOUT_S)
        yield Fleet(broker, servers, view, time.perf_counter() - began_s)


async def start_machine(stack: contextlib.AsyncExitStack, folder: Path, broker: Broker,
                        index: int) -> Served:
    place = folder / slug(index)
    place.mkdir()
    extra = f'[machine]\nname = "{slug(index)}"\n' + mqtt_toml(broker, allow_control=True)
    served: Served = await stack.enter_async_context(motiond(place, extra))
    return served


async def idle(fleet: Fleet) -> dict[str, float]:
    """CPU (% of a core) and RSS (MB) of each instance and of the broker over IDLE_S."""
    assert fleet.broker.process is not None
    pids = [served.process.pid for served in fleet.servers]
    broker_pid = fleet.broker.process.pid
    before = {pid: usage(pid)[0] for pid in [*pids, broker_pid]}
    await asyncio.sleep(IDLE_S)
    after = {pid: usage(pid) for pid in [*pids, broker_pid]}
    cpu = sorted(100.0 * (after[pid][0] - before[pid]) / IDLE_S for pid in pids)
    rss = sorted(after[pid][1] / 1e6 for pid in pids)
    return {"cpu_pct_median": cpu[len(cpu) // 2], "cpu_pct_max": cpu[-1],
            "cpu_pct_total": sum(cpu), "rss_mb_median": rss[len(rss) // 2],
            "rss_mb_max": rss[-1],
            "broker_cpu_pct": 100.0 * (after[broker_pid][0] - before[broker_pid]) / IDLE_S,
            "broker_rss_mb": after[broker_pid][1] / 1e6}


def discovery_configs(fleet: Fleet) -> list[int]:
    """The Home Assistant configs retained for each machine."""
    topics = {topic for topic, _ in fleet.view.messages if topic.startswith("homeassistant/")}
    return [sum(f"/{slug(index)}/" in topic for topic in topics)
            for index in range(len(fleet.servers))]


async def staleness(fleet: Fleet, spacing_s: float, x_mm: float = 5.0) -> list[float]:
    """Command ``G0 X..`` (a move of well under 0.1 s) to every machine, one after another
    ``spacing_s`` apart (0: as fast as the broker takes them, every machine moving at
    once); for each, the seconds from its own command to the
    fleet's view showing it idle at the new position: the command's way there, the move, and
    the status's way back (at most ``status_hz``, 2 a second by default)."""
    view, count = fleet.view, len(fleet.servers)
    sent_s = [0.0] * count

    first = len(view.messages)  # only what comes from now on

    async def seen(index: int) -> float:  # watching from before the command is sent
        topic, looked = f"motiond/{slug(index)}/status", first
        for _ in range(int(60 / POLL_S)):  # (polled: many waiters share the view)
            for got, payload in view.messages[looked:]:
                status = json.loads(payload) if got == topic else None
                if status and status["state"] == "Idle" and status["mpos"][0] == x_mm:
                    return time.perf_counter() - sent_s[index]
            looked = len(view.messages)
            await asyncio.sleep(POLL_S)
        raise TimeoutError(f"{topic}: no idle status at X{x_mm:g}")

    watchers = [asyncio.create_task(seen(index)) for index in range(count)]
    await asyncio.sleep(0)
    for index in range(count):
        sent_s[index] = time.perf_counter()
        await view.publish(f"motiond/{slug(index)}/cmd/gcode",
                           {"id": f"s{index}", "lines": [f"G0 X{x_mm:g}"]})
        await asyncio.sleep(spacing_s)
    return list(await asyncio.gather(*watchers))


async def fleet_listing(fleet: Fleet) -> list[dict[str, Any]]:
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.cli", "fleet", "--url", fleet.broker.url, "--json",
        "--wait-s", "1.5", cwd=REPO, env=os.environ.copy(), stdout=asyncio.subprocess.PIPE)
    out, _ = await asyncio.wait_for(process.communicate(), 60)
    rows: list[dict[str, Any]] = json.loads(out.decode())
    return rows


async def job_through_broker(fleet: Fleet, index: int) -> dict[str, Any]:
    """Send a job to machine ``index`` through the broker; its end event."""
    (fleet.servers[index].jobs_dir / "square.nc").write_text(JOB)
    topic = f"motiond/{slug(index)}"
    await fleet.view.publish(f"{topic}/cmd/job", {"id": "job", "name": "square.nc"})
    reply = await fleet.view.wait_json(f"{topic}/reply", lambda r: r["id"] == "job")
    if not reply["ok"]:
        return reply
    end: dict[str, Any] = await fleet.view.wait_json(
        f"{topic}/event/job", lambda e: e["event"] == "end", timeout_s=60)
    return end


async def measure(count: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as folder:
        async with fleet(Path(folder), count) as machines:
            figures: dict[str, Any] = {"machines": count, "start_s": machines.started_s}
            figures.update(await idle(machines))
            figures["discovery"] = min(discovery_configs(machines))
            stale = sorted(await staleness(machines, SPACING_S))
            together = sorted(await staleness(machines, 0.0, x_mm=0.0))
            figures.update(together_p50_s=together[len(together) // 2],
                           together_max_s=together[-1])
            figures.update(stale_p50_s=stale[len(stale) // 2], stale_max_s=stale[-1])
            rows = await fleet_listing(machines)
            figures["listed_online"] = sum(row["availability"] == "online" for row in rows)
            end = await job_through_broker(machines, count // 2)
            figures["job"] = (end.get("job") or {}).get("state")
            return figures


def run(quick: bool, machines: int | None = None) -> BenchResult:
    result = BenchResult("fleet", quick)
    count = machines or (QUICK_MACHINES if quick else MACHINES)
    figures = asyncio.run(measure(count))
    print(f"{count} machines on one mosquitto: online in {figures['start_s']:.1f} s")
    print(f"idle over {IDLE_S:g} s: CPU per instance median {figures['cpu_pct_median']:.2f} %, "
          f"max {figures['cpu_pct_max']:.2f} %, all {figures['cpu_pct_total']:.1f} % of a core; "
          f"RSS median {figures['rss_mb_median']:.0f} MB, max {figures['rss_mb_max']:.0f} MB; "
          f"broker {figures['broker_cpu_pct']:.2f} % CPU, {figures['broker_rss_mb']:.1f} MB")
    print(f"Home Assistant discovery: {figures['discovery']} configs for every machine")
    verdict = "OK" if figures["stale_max_s"] <= STALE_GOAL_S else "OVER"
    print(f"staleness (G0 to each, {SPACING_S * 1000:g} ms apart, until the view shows it "
          f"idle at its new place): p50 {figures['stale_p50_s']:.2f} s, worst "
          f"{figures['stale_max_s']:.2f} s (goal: state within {STALE_GOAL_S:g} s) {verdict}; "
          f"every machine moving at once: p50 {figures['together_p50_s']:.2f} s, worst "
          f"{figures['together_max_s']:.2f} s")
    print(f"motiond fleet --json: {figures['listed_online']} of {count} online; job through "
          f"the broker: {figures['job']}")
    result.add("fleet", f"{count} machines", **{
        key: (value, unit) for key, unit in (
            ("start_s", "s"), ("cpu_pct_median", "%"), ("cpu_pct_max", "%"),
            ("cpu_pct_total", "%"), ("rss_mb_median", "MB"), ("rss_mb_max", "MB"),
            ("broker_cpu_pct", "%"), ("broker_rss_mb", "MB"), ("stale_p50_s", "s"),
            ("stale_max_s", "s"), ("together_p50_s", "s"), ("together_max_s", "s"))
        for value in [figures[key]]})
    return result


if __name__ == "__main__":
    sys.exit(standalone(run, __doc__.splitlines()[0]))
