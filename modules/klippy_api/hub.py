"""What every session of the API socket shares: the :class:`Hub` (implemented by the
``[klippy_api]`` module), so a session and its scripts are tested without a socket."""

from __future__ import annotations

from typing import Any, Protocol

from modules.klippy_api.budget import ByteBudget, LoopBudget
from server.kernel.module import ModuleContext


class Hub(Protocol):
    """What a session needs of the module (shared by every session).

    ``budget`` is the event-loop time all connections draw on; ``script_bytes`` the memory
    all their waiting scripts may hold."""

    ctx: ModuleContext
    jog_feed_mm_min: float
    budget: LoopBudget
    script_bytes: ByteBudget
    job_state: str | None  # the last job's state (running, paused, done...), None before

    def objects(self) -> dict[str, Any]:
        """Every printer object now (one snapshot per loop turn, shared: read only)."""
        ...

    def info(self) -> dict[str, Any]: ...

    def set_message(self, text: str | None) -> None: ...

    def output(self, text: str) -> None:
        """Send a G-code response line to every output subscriber."""
        ...

    def restart(self) -> None:
        """Close every API connection (after RESTART/FIRMWARE_RESTART)."""
        ...
