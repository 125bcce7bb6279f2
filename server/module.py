"""The module contract: a plug-in is a class with a name, a config model and an async ``run()``.

A module is registered declaratively under the ``motiond.modules`` entry point group, so a
third-party package adds one with a line in its own ``pyproject.toml``::

    [project.entry-points."motiond.modules"]
    mymodule = "my_package.mymodule:MyModule"

A config section ``[mymodule]`` then instantiates it; a module with ``named = True`` is
configured as ``[mymodule.NAME]`` with one instance per name. The module reads its config in
``__init__``, may look up peers only from ``run()`` on, and reaches the core only through its
:class:`ModuleContext`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from pydantic import BaseModel, ConfigDict

if TYPE_CHECKING:
    from server.clock import Clock
    from server.dispatcher import Handler
    from server.events import MachineState
    from server.machine import Machine
    from server.moves import Action
    from server.stepgen import MotionState

ENTRY_POINT_GROUP = "motiond.modules"


class ModuleConfig(BaseModel):
    """Base for module config models: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ModuleContext(Protocol):
    """What a module may use of the kernel (DESIGN.md rule 2)."""

    name: str  # the section: "laser" or "switch.fan"
    log: logging.Logger
    clock: Clock

    def register_command(self, name: str, handler: Handler, *, when_locked: bool = False) -> None:
        """Handle a G/M code ("M106"), a $ command ("$H") or a named command ("fire")."""
        ...

    def subscribe(self, event: str, callback: Callable[..., None]) -> None:
        """Call ``callback(*args)`` synchronously whenever the kernel emits ``event``."""
        ...

    def lookup(self, name: str) -> Module:
        """Another configured module by section name; raises KeyError if absent."""
        ...

    def motion(self) -> MotionState:
        """The step generator's latest published motion state."""
        ...

    async def queue_action(self, action: Action) -> None:
        """Queue an action to run in order with motion (waits while the planner is full)."""
        ...

    def alarm(self, message: str, code: int = 0) -> None:
        """Put the machine in ALARM: motion stops, tools go off, the reason is reported."""
        ...

    def emit(self, event: str, *args: Any) -> None:
        """Emit a kernel event (for example a module's own state change)."""
        ...

    def set_state(self, state: MachineState) -> None:
        """Set the machine state (homing shows ``Home``)."""
        ...

    @property
    def machine(self) -> Machine:
        """The motion pipeline: its backend (outputs, switches), G-code handler, positions."""
        ...

    def clear_alarm(self) -> None:
        """Unlock after an alarm, as ``$X`` does (homing unlocks in Grbl)."""
        ...


class Module:
    """Base class of modules. Subclasses set ``name`` and ``Config`` and override ``run``."""

    name: ClassVar[str]
    Config: ClassVar[type[BaseModel]] = ModuleConfig
    named: ClassVar[bool] = False

    def __init__(self, ctx: ModuleContext, config: Any) -> None:
        self.ctx = ctx
        self.config = config

    async def run(self) -> None:
        """The module's task. Returning ends it quietly; raising alarms the machine."""

    def status(self) -> dict[str, Any]:
        """A small JSON-able summary for status reports and the web UI."""
        return {}

    def report_pins(self) -> str:
        """Letters this module contributes to the status report's ``Pn:`` field."""
        return ""


def available_modules() -> dict[str, type[Module]]:
    """Every module registered under the entry point group, by section name."""
    found: dict[str, type[Module]] = {}
    for entry in entry_points(group=ENTRY_POINT_GROUP):
        cls = entry.load()
        found[entry.name] = cls
    return found
