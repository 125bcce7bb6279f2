"""10,000 malformed control messages through a real broker: no crash, no motion, every one
refused (or counted as dropped), the loop never stalls past the budget and the server answers.

The server runs in this process (so its own loop-stall measurement can be read); the flood
comes from another process, as an attacker's client would.
"""

from __future__ import annotations

import asyncio
import sys
import textwrap
from pathlib import Path

from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.transports.tcp import TcpTransport
from tests.conftest import REPO, make_config
from tests.support.broker import mosquitto, watching
from tests.support.helpers import running

FLOOD = 10_000
STALL_BOUND_S = 0.25  # generous on a shared two-core machine (as in test_hostile_input)
CPU_STALL_BOUND_S = 0.05  # the process's own work (measured: about 2 ms)
PREFIX = "motiond/flooded"
FLOODER = textwrap.dedent('''
    import asyncio, sys, aiomqtt
    PAYLOADS = [
        b"\\xff\\xfe", b"not json", b"[1, 2]", b"null", b"[" * 50_000, b"x" * 70_000,
        b'{"id": {"x": 1}, "lines": ["G0 X10"]}', b'{"id": 1, "lines": ["G0 X10\\\\u0018"]}',
        b'{"id": 1, "lines": ["G0 X10"], "extra": 1}', b'{"id": 1, "lines": []}',
        b'{"id": 1, "lines": [5]}', b'{"command": "explode"}', b"HOLD!", b'{"id": 1, "name": 5}',
        b'{"id": 1, "name": ""}', b'{"id": true, "name": "a.nc"}',
    ]
    TOPICS = ["gcode", "realtime", "job", "unknown"]
    async def main(port: int, prefix: str, count: int) -> None:
        async with aiomqtt.Client("127.0.0.1", port, max_inflight_messages=200) as client:
            for start in range(0, count, 200):
                await asyncio.gather(*(
                    client.publish(f"{prefix}/cmd/{TOPICS[i % 4]}", PAYLOADS[i % len(PAYLOADS)], 1)
                    for i in range(start, min(count, start + 200))))
    asyncio.run(main(int(sys.argv[1]), sys.argv[2], int(sys.argv[3])))
''')


async def tcp_report(port: int) -> str:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        await asyncio.wait_for(reader.readuntil(b"for help]"), 5)
        writer.write(b"?")
        await writer.drain()
        return (await asyncio.wait_for(reader.readuntil(b">"), 5)).decode().strip()
    finally:
        writer.close()


async def test_a_flood_of_malformed_commands_moves_nothing_and_stalls_nothing(
    tmp_path: Path,
) -> None:
    async with mosquitto(tmp_path / "broker") as broker:
        config = make_config({"machine": {"name": "flooded"}, "mqtt": {
            "url": broker.url, "allow_control": True}})
        async with running(config, RealClock(), transports=[TcpTransport]) as app:
            module = app.kernel.modules["mqtt"]
            port = next(t.port for t in app.transports if isinstance(t, TcpTransport))
            async with watching(broker, f"{PREFIX}/availability") as watch:
                await watch.wait_for(f"{PREFIX}/availability", lambda p: p == b"online")
            app.kernel.loop_monitor.reset()
            flooder = await asyncio.create_subprocess_exec(
                sys.executable, "-c", FLOODER, str(broker.port), PREFIX, str(FLOOD), cwd=REPO)
            assert await asyncio.wait_for(flooder.wait(), 60) == 0
            async with asyncio.timeout(30):
                while module.control.refused + module.link.dropped_incoming < FLOOD:  # noqa: ASYNC110
                    await asyncio.sleep(0.05)
            stall_s = app.kernel.loop_monitor.worst_stall_s
            cpu_stall_s = app.kernel.loop_monitor.worst_cpu_stall_s
            report = await tcp_report(port)
            state = app.kernel.state
            position = app.kernel.machine.stepgen.state.position_mm
            refused, dropped = module.control.refused, module.link.dropped_incoming
            connected = module.link.connected
    assert refused + dropped == FLOOD, "every message refused or counted, none obeyed"
    assert state is MachineState.IDLE and position == (0.0, 0.0, 0.0)
    assert report.startswith("<Idle|MPos:0.000,0.000,0.000")
    assert connected, "the module is still up and connected"
    assert stall_s < STALL_BOUND_S, f"the loop stalled {stall_s * 1000:.0f} ms"
    assert cpu_stall_s < CPU_STALL_BOUND_S, f"own work stalled {cpu_stall_s * 1000:.0f} ms"
