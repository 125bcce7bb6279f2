"""A fleet of five ``motiond`` on one Mosquitto (the fleet benchmark's run, small): every
machine's state reaches the fleet's view within a second, each publishes its Home Assistant
discovery, ``motiond fleet`` lists them all online, and a job sent through the broker runs."""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_fleet import (
    STALE_GOAL_S,
    discovery_configs,
    fleet,
    fleet_listing,
    job_through_broker,
    staleness,
)

MACHINES = 5


async def test_five_machines_on_one_broker_are_seen_within_a_second(tmp_path: Path) -> None:
    async with fleet(tmp_path, MACHINES) as machines:
        stale_s = await staleness(machines, 0.0)  # all at once
        configs = discovery_configs(machines)
        rows = await fleet_listing(machines)
        end = await job_through_broker(machines, 2)
    assert len(stale_s) == MACHINES
    assert max(stale_s) < STALE_GOAL_S, stale_s
    assert min(configs) >= 2, "Home Assistant discovery for every machine"
    assert sorted((row["machine"], row["availability"]) for row in rows) == [
        (f"m{index:02d}", "online") for index in range(MACHINES)]
    assert end["event"] == "end" and end["job"]["state"] == "done"
    assert end["machine"] == "m02" and end["job"]["name"] == "square.nc"
