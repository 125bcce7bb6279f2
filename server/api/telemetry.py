"""Status and telemetry for JSON API subscribers: sampled at a bounded rate, encoded once.

:class:`Publisher` owns one task. While anyone subscribes, it samples the machine at most
``rate_hz`` times a second (loop time: this bounds network traffic, not motion), builds the
status object, and when it differs from the last one encodes a single JSON-RPC notification
that every subscriber's :class:`Channel` receives as the same string. Telemetry (speed and
laser power for plots) is sent alongside while the machine moves. Console lines (the kernel's
``push`` event) and job updates go out at once, encoded once too.

A :class:`Channel` is a client's bounded queue of outgoing frames. When it is full the client is
not keeping up: the channel closes itself and calls its ``on_overflow`` (the transport aborts
the connection). Nobody ever waits for a slow client.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from server.kernel.status import build_status, job_dict, tool_power_pct
from server.runtime.events import Event, MachineState
from server.sessions.outbox import BoundedQueue

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

log = logging.getLogger("motiond.telemetry")
QUEUE_FRAMES = 256
TOPICS = frozenset({"status", "telemetry", "console", "job"})
_WAKE_EVENTS = (
    "state",
    "halt",
    "clear_halt",
    "hold",
    "hold_stopped",
    "resume",
    "override",
    "action",
    "program_end",
    "job",
)
_BUSY_STATES = frozenset({MachineState.RUN, MachineState.JOG, MachineState.HOME, MachineState.HOLD})


def encode(message: dict[str, Any]) -> str:
    """One JSON text frame (compact, no NaN)."""
    return json.dumps(message, separators=(",", ":"), allow_nan=False)


def notification(method: str, params: dict[str, Any]) -> str:
    """An encoded JSON-RPC 2.0 notification."""
    return encode({"jsonrpc": "2.0", "method": method, "params": params})


class Channel(BoundedQueue[str]):
    """One API client's bounded queue of encoded frames, drained frame by frame."""

    def __init__(self, limit_frames: int = QUEUE_FRAMES) -> None:
        super().__init__(limit_frames, size=lambda frame: 1)
        self.topics: set[str] = set()

    def offer(self, frame: str) -> bool:
        """Queue a frame; False (and the channel closes) when the client is not keeping up."""
        return self.put(frame)

    async def get(self) -> str | None:
        """The next frame, or None once the channel is closed."""
        return await self.get_one()


class Publisher:
    """Samples the kernel and fans encoded notifications out to subscribed channels."""

    def __init__(self, kernel: Kernel, rate_hz: float = 20.0, idle_period_s: float = 0.5) -> None:
        self.kernel = kernel
        self.period_s = 1.0 / rate_hz
        self.idle_period_s = idle_period_s
        self.channels: set[Channel] = set()
        self.encoded = 0  # notifications encoded so far (each once, whatever the audience)
        self.dropped = 0  # channels dropped for not keeping up
        self._wake = asyncio.Event()
        self._last_status: dict[str, Any] | None = None
        self._last_telemetry: tuple[float, float] | None = None
        self._unsubscribe: list[Callable[[], None]] = []

    # -- subscriptions ----------------------------------------------------------------------
    def subscribe(self, channel: Channel, topics: set[str]) -> None:
        channel.topics |= topics
        self.channels.add(channel)
        self._last_status = None  # a new subscriber gets the next status in full
        self._wake.set()

    def unsubscribe(self, channel: Channel, topics: set[str] | None = None) -> None:
        channel.topics -= channel.topics if topics is None else topics
        if not channel.topics:
            self.channels.discard(channel)

    def wake(self) -> None:
        """Something changed: sample soon (still at most ``rate_hz``)."""
        self._wake.set()

    # -- fan-out ----------------------------------------------------------------------------
    def broadcast(self, topic: str, method: str, params: dict[str, Any]) -> int:
        """Encode once and offer to every channel subscribed to ``topic``; returns receivers."""
        audience = [channel for channel in self.channels if topic in channel.topics]
        if not audience:
            return 0
        frame = notification(method, params)
        self.encoded += 1
        for channel in audience:
            if not channel.offer(frame):
                self.dropped += 1
                self.channels.discard(channel)
                log.warning("dropped a JSON API subscriber that is not keeping up")
        return len(audience)

    # -- the task ---------------------------------------------------------------------------
    async def run(self) -> None:
        """Publish until cancelled."""
        events = self.kernel.events
        self._unsubscribe = [
            events.subscribe(name, lambda *_: self.wake()) for name in _WAKE_EVENTS
        ]
        self._unsubscribe.append(events.subscribe(Event.PUSH, self._on_push))
        self._unsubscribe.append(events.subscribe(Event.JOB, self._on_job))
        loop = asyncio.get_running_loop()
        try:
            while True:
                while not self.channels:
                    self._wake.clear()
                    await self._wake.wait()
                started = loop.time()
                self._wake.clear()  # what happens from now on wakes the next round
                try:
                    moving = self.publish_once()
                except Exception:  # noqa: BLE001 - a bad sample must not end the publisher
                    log.exception("could not publish the status")
                    moving = False
                await asyncio.sleep(max(0.0, started + self.period_s - loop.time()))
                if not moving:
                    # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancel
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(self.idle_period_s):
                            await self._wake.wait()
        finally:
            for unsubscribe in self._unsubscribe:
                unsubscribe()

    def publish_once(self) -> bool:
        """Sample now; send status if it changed and telemetry while moving. True while busy."""
        status = build_status(self.kernel)
        if status != self._last_status:
            self._last_status = status
            self.broadcast("status", "notify_status_update", {"status": status})
        sample = telemetry_sample(self.kernel)
        point = (sample["speed_mm_min"], sample["power_pct"])
        moving = bool(status["moving"])
        if moving or point != self._last_telemetry:
            self._last_telemetry = point
            self.broadcast("telemetry", "notify_telemetry", sample)
        return moving or self.busy()

    def busy(self) -> bool:
        """Whether things are about to change: motion queued, a cycle or a job under way."""
        kernel = self.kernel
        return (
            kernel.state in _BUSY_STATES or len(kernel.machine.planner) > 0 or kernel.jobs.running
        )

    def _on_push(self, message: str) -> None:
        self.broadcast("console", "notify_gcode_response", {"message": message})
        self.wake()

    def _on_job(self, progress: Any) -> None:
        job = None if progress is None else job_dict(progress)
        self.broadcast("job", "notify_job_update", {"job": job})


# -- what is published ----------------------------------------------------------------------
def telemetry_sample(kernel: Kernel) -> dict[str, Any]:
    """One point for the live plots: machine time, speed and tool power."""
    motion = kernel.machine.stepgen.state
    return {
        "t_s": round(kernel.clock.now_s(), 4),
        "speed_mm_min": round(motion.speed_mm_s * 60.0, 1),
        "power_pct": round(tool_power_pct(kernel), 1),
        "s": motion.s_value if motion.moving else kernel.machine.tool.s,
    }
