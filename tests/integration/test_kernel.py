"""The kernel: module registration and supervision, events, state, shutdown order."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from typing import Any, ClassVar

import pytest
from pydantic import Field

from server.app import App
from server.config_loader import build_config
from server.errors import CommandError
from server.kernel.module import Module, ModuleConfig, available_modules
from server.runtime.clock import VirtualClock
from server.runtime.dispatcher import Command
from server.runtime.events import MachineState
from tests.conftest import BASE, REPO
from tests.support.helpers import SOURCE, running, submit_all


class BoomConfig(ModuleConfig):
    after_s: float = Field(1.0, gt=0)


class Boom(Module):
    """Raises after a while, like a module with a bug."""

    name = "boom"
    Config = BoomConfig

    async def run(self) -> None:
        await self.ctx.clock.sleep_until(self.ctx.clock.now_s() + self.config.after_s)
        raise RuntimeError("sensor unplugged")


class PumpConfig(ModuleConfig):
    pin: str


class Pump(Module):
    """A named output with its own command; turns itself off on halt and shutdown."""

    name = "pump"
    Config = PumpConfig
    named: ClassVar[bool] = True

    def __init__(self, ctx: Any, config: PumpConfig) -> None:
        super().__init__(ctx, config)
        self.on = False
        ctx.register_command(f"pump_{ctx.name.split('.')[1]}", self._command)
        ctx.subscribe("halt", lambda reason: self._set(False))
        ctx.subscribe("shutdown", lambda: self._set(False))

    def _command(self, command: Command) -> list[str]:
        self._set(command.args.strip() == "on")
        return [f"[MSG:{self.ctx.name} {'on' if self.on else 'off'}]"]

    def _set(self, on: bool) -> None:
        self.on = on
        self.ctx.outputs.set(self.config.pin, float(on))


REGISTRY = {"boom": Boom, "pump": Pump, **available_modules()}


def config_with(**sections: Any):
    return build_config({**BASE, **sections}, "test.toml", REGISTRY)


def test_modules_are_registered_through_entry_points() -> None:
    assert available_modules()["heartbeat"].__name__ == "Heartbeat"


def test_named_instances_give_several_modules_of_one_kind() -> None:
    config = config_with(pump={"coolant": {"pin": "P1"}, "vacuum": {"pin": "P2"}})
    assert [(spec.section, spec.instance) for spec in config.modules] == [
        ("pump.coolant", "coolant"), ("pump.vacuum", "vacuum")]


async def test_module_handlers_are_reached_through_the_dispatcher() -> None:
    config = config_with(pump={"coolant": {"pin": "P1"}})
    async with running(config) as app:
        assert await submit_all(app, ["pump_coolant on"]) == [["[MSG:pump.coolant on]"]]
        assert app.kernel.machine.backend.output("P1") == 1.0


async def test_heartbeat_counts_second_ticks_and_answers_its_command() -> None:
    async with running(config_with(heartbeat={})) as app:
        await app.clock.sleep(3.5)  # type: ignore[attr-defined]
        (reply,) = await submit_all(app, ["heartbeat"])
        assert reply == ["[MSG:heartbeat beats=3 uptime=3.5s]"]


async def test_a_crashing_module_alarms_the_machine_and_the_server_keeps_answering() -> None:
    pushed: list[str] = []
    config = config_with(boom={"after_s": 0.5}, pump={"coolant": {"pin": "P1"}})
    async with running(config) as app:
        kernel = app.kernel
        kernel.events.subscribe("push", pushed.append)
        await submit_all(app, ["pump_coolant on", "G1 X100 F600"])
        await app.clock.sleep(1.0)  # type: ignore[attr-defined]
        assert kernel.state is MachineState.ALARM
        assert pushed[0] == "ALARM:41"
        assert "[boom]" in pushed[1] and "sensor unplugged" in pushed[1]
        assert kernel.machine.backend.output("P1") == 0.0, "tools go off on alarm"
        assert not kernel.machine.stepgen.state.moving
        with pytest.raises(CommandError) as info:
            await kernel.dispatcher.submit("G1 X10", SOURCE)
        assert info.value.code == 9
        assert await submit_all(app, ["$X", "G0 X5"]) == [[], []]
        assert kernel.state is not MachineState.ALARM


class RecordingTransport:
    name = "recorder"

    def __init__(self, kernel: Any) -> None:
        self.kernel = kernel
        self.outputs_at_close: float | None = None

    async def start(self) -> None:
        pass

    async def close(self) -> None:
        self.outputs_at_close = self.kernel.machine.backend.output("P1")


async def test_shutdown_turns_tools_off_before_transports_close() -> None:
    transports: list[RecordingTransport] = []

    def factory(kernel: Any) -> RecordingTransport:
        transports.append(RecordingTransport(kernel))
        return transports[-1]

    app = App(config_with(pump={"air": {"pin": "P1"}}), clock=VirtualClock(), transports=[factory])
    task = asyncio.create_task(app.run())
    await app.ready.wait()
    await app.kernel.dispatcher.submit("pump_air on", SOURCE)
    await app.kernel.dispatcher.submit("G1 X50 F600", SOURCE)
    app.request_stop()
    app.request_stop()  # repeated stops are harmless
    await asyncio.wait_for(task, 2)
    assert transports[0].outputs_at_close == 0.0
    assert app.closed_order == ["tools-off", "close:recorder"]
    assert app.kernel.stopped


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_motiond_exits_cleanly_on_a_signal_within_two_seconds(signum: int) -> None:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "--tcp-port", "0", "--http-port", "0"],
        cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    assert process.stderr is not None
    deadline = time.monotonic() + 20
    seen = ""
    while "HTTP/WebSocket listening" not in seen and time.monotonic() < deadline:
        seen += process.stderr.readline()
    assert "TCP listening" in seen
    started = time.monotonic()
    process.send_signal(signum)
    process.send_signal(signum)  # a second signal is harmless
    assert process.wait(timeout=5) == 0
    assert time.monotonic() - started < 2.0
    rest = process.stderr.read()
    assert "Traceback" not in rest and "stopped" in rest
