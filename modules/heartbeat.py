"""``[heartbeat]``: the smallest real module, proving the module contract.

It counts the kernel's second ticks, answers the named command ``heartbeat`` with the uptime
and the number of beats, and, with ``log_every_s`` set, logs a line at that interval.

    [heartbeat]
    log_every_s = 60
"""

from __future__ import annotations

from typing import Any

from pydantic import Field

from server.kernel.module import Module, ModuleConfig, ModuleContext
from server.runtime.dispatcher import Command
from server.runtime.events import Event


class HeartbeatConfig(ModuleConfig):
    log_every_s: int = Field(0, ge=0, description="log a beat line every N seconds (0: never)")


class Heartbeat(Module):
    """Counts seconds; answers ``heartbeat``."""

    name = "heartbeat"
    Config = HeartbeatConfig

    def __init__(self, ctx: ModuleContext, config: HeartbeatConfig) -> None:
        super().__init__(ctx, config)
        self.beats = 0
        self.started_s = ctx.clock.now_s()
        ctx.subscribe(Event.SECOND, self._on_second)
        ctx.register_command("heartbeat", self._command, when_locked=True, query=True)

    def _on_second(self, now_s: float) -> None:
        self.beats += 1
        every = self.config.log_every_s
        if every and self.beats % every == 0:
            self.ctx.log.info("heartbeat: %d beats", self.beats)

    def _command(self, command: Command) -> list[str]:
        uptime_s = self.ctx.clock.now_s() - self.started_s
        return [f"[MSG:heartbeat beats={self.beats} uptime={uptime_s:.1f}s]"]

    def status(self) -> dict[str, Any]:
        return {"beats": self.beats}

