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

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from pydantic import BaseModel, ConfigDict

if TYPE_CHECKING:
    from server.config import CoreConfig
    from server.gcode.codes import CodeFactory
    from server.machine.machine import SyncHandler
    from server.motion.motion_state import MotionState
    from server.motion.moves import Action, Move, Position, SyncKind
    from server.motion.pieces import PowerOf
    from server.runtime.clock import Clock
    from server.runtime.dispatcher import Handler
    from server.runtime.events import MachineState

ENTRY_POINT_GROUP = "motiond.modules"


class ModuleConfig(BaseModel):
    """Base for module config models: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ApiParams(BaseModel):
    """Base for the parameters of a module's JSON-RPC method: unknown keys, NaN and Infinity
    are invalid params."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class ApiCaller(Protocol):
    """The connection calling a module's JSON-RPC method."""

    async def submit(self, line: str) -> list[str]:
        """Run one line as that connection (its rights, in order with its other lines)."""
        ...


ApiHandler = Callable[[Any, ApiCaller], Awaitable[Any]]


@dataclass(frozen=True, slots=True)
class ApiMethod:
    """A JSON-RPC method a module contributes: ``handler(params, caller)``."""

    name: str
    handler: ApiHandler
    params: type[BaseModel]
    control: bool


class Outputs(Protocol):
    """The machine's output pins (laser PWM, spindle, fan): duty cycles in [0, 1], set now."""

    def set(self, pin: str, value: float) -> None: ...

    def declare_tool(self, pin: str) -> None:
        """``pin`` drives the tool (its duty is the tool power in traces and history)."""
        ...

    def value(self, pin: str) -> float: ...

    def follow_motion(self, pin: str, power_of: PowerOf, period_s: float) -> bool:
        """Let the backend time ``pin`` from the trajectory (``power_of(move, nominal_mm_s)``
        per block, updated at most every ``period_s``): True where it can (a Klipper MCU),
        else False and the module sets the pin itself."""
        ...


class Inputs(Protocol):
    """The machine's switch inputs, read where the tool physically is."""

    def switch_triggered(self, name: str) -> bool: ...

    def place_switch(self, name: str, at_mm: float) -> None:
        """Simulated machines: where a switch sits on its axis (real machines ignore it)."""
        ...


class Motion(Protocol):
    """Moves outside G-code (homing), and the motion pipeline's controls. Units: mm, mm/s."""

    tick_s: float  # the step generator's tick period

    async def queue_move(self, move: Move) -> None:
        """Append a move; waits while the planner is full."""
        ...

    async def wait_idle(self) -> None:
        """Wait until every queued move has run."""
        ...

    def stop_now(self) -> None:
        """Stop motion at once, discarding what is queued (tools stay as they are)."""
        ...

    def set_position(self, position_mm: Position) -> None:
        """Redefine the machine position without moving (homing)."""
        ...


class MachineControls(Protocol):
    """Realtime control, acted on at once: exactly what ``!``, ``~``, Ctrl-X and an arriving
    M112 or M410 do on any connection (one implementation:
    ``server.kernel.control.MachineControl``).
    """

    def hold(self) -> None:
        """Feed hold: decelerate to a stop on the path; a running job is paused."""
        ...

    def resume(self) -> None:
        """Cycle start: continue where the hold stopped; a paused job plays on."""
        ...

    def reset(self) -> None:
        """Soft reset: stop at once and flush (ALARM:3 if it was moving); a job ends."""
        ...

    def emergency_stop(self) -> None:
        """M112 on arrival: ALARM:40, motion stopped and tools off until ``$X`` or M999."""
        ...

    def cancel_job(self) -> None:
        """Abort the running or paused job (Smoothie's ``abort``); nothing without one."""
        ...

    def set_feed_override(self, percent: int) -> None:
        """The feed override in percent, clamped to 10-200 (what 0x90-0x94 change)."""
        ...

    def quickstop(self) -> None:
        """M410 on arrival: motion stopped, queue flushed, tools off; no alarm; a job ends."""
        ...


class ModuleContext(Protocol):
    """What a module may use of the core (DESIGN.md rule 2): narrow ports, not the machine."""

    name: str  # the section: "laser" or "switch.fan"
    log: logging.Logger
    clock: Clock
    core: CoreConfig  # the machine's config, read-only

    @property
    def outputs(self) -> Outputs: ...

    @property
    def inputs(self) -> Inputs: ...

    @property
    def moves(self) -> Motion: ...

    @property
    def control(self) -> MachineControls:
        """Hold, resume and reset, the same for a module as for every connection."""
        ...

    def register_command(
        self, name: str, handler: Handler, *, when_locked: bool = False, query: bool = False
    ) -> None:
        """Handle a ``$`` command ("$H") or a named command ("fire")."""
        ...

    def register_code(
        self,
        code: int,
        factory: CodeFactory,
        *,
        group: str | None = None,
        uses: str = "",
        query: bool = False,
        key: tuple[str, str] | None = None,
    ) -> None:
        """Claim ``M<code>`` with the interpreter (see :mod:`server.gcode.codes`)."""
        ...

    def register_sync(self, kind: SyncKind, handler: SyncHandler) -> None:
        """Carry out the interpreter's ``Sync(kind)`` requests (``home`` for G28.2)."""
        ...

    def set_spin_up_delay(self, seconds: float) -> None:
        """Motion waits ``seconds`` after M3/M4 starts a stopped spindle."""
        ...

    async def run_gcode(self, text: str, ticket: int | None = None) -> list[str]:
        """Run one line in order with every other source, as the module. ``ticket``: the
        stop generation the request was made in (:meth:`ticket`; default now): a line asked
        for before a stop is refused (error 45), never run after it."""
        ...

    def run_in_job(self, text: str, ticket: int) -> asyncio.Future[list[str] | None] | None:
        """Queue one line to run as part of the running or paused job, before its next line,
        in order with its motion (a baby-step: ``M290 Z0.05``); None when no job plays. The
        future is the line's messages once it ran, a :class:`~server.errors.CommandError`
        when it was refused (45 after a stop since ``ticket``), or None when the job ended
        before its turn: nothing ran (run it with :meth:`run_gcode`, under the same ticket).
        Raises CommandError 45 when too many lines wait."""
        ...

    async def start_job(self, name: str, ticket: int | None = None) -> None:
        """Check and play the stored job file ``name``, as the JSON API's ``job.start`` does;
        raises :class:`~server.errors.CommandError` (47 does not fit the travel from the
        current work origin, 45 busy or stopped meanwhile, 44 no such file) and changes
        nothing. ``ticket`` as for :meth:`run_gcode`."""
        ...

    def ticket(self) -> int:
        """The stop generation now: what a request made now carries (see
        :mod:`server.runtime.state`)."""
        ...

    def still_valid(self, ticket: int) -> bool:
        """Whether no stop came since ``ticket`` was taken."""
        ...

    def status(self) -> dict[str, Any]:
        """The machine now, as the web UI's status shows it (JSON-able: state, alarm and its
        meaning, positions, speed, tool power, queue, the job with its progress); the one
        snapshot of :func:`server.kernel.status.build_status`, built on each call."""
        ...

    def register_api_method(
        self,
        name: str,
        handler: ApiHandler,
        params: type[BaseModel] = ApiParams,
        *,
        control: bool = False,
    ) -> None:
        """Serve the JSON-RPC method ``name`` (``laser.fire``); ``control`` methods need a
        connection that may control the machine."""
        ...

    def add_status_field(self, name: str, read: Callable[[], Any]) -> None:
        """A top-level field of every status update (``power_pct``), read when it is sent."""
        ...

    def add_feature(self, name: str) -> None:
        """Tell clients what this machine can do (``laser``, ``homing``): ``server.info``."""
        ...

    def register_setting(self, number: int, description: str, read: Callable[[], float],
                         write: Callable[[float], None], *, high: float) -> None:
        """Own Grbl setting ``$number`` (``$23``-``$27``: homing): ``$$`` lists ``read()``,
        ``$number=v`` calls ``write(v)`` once v is a number in 0..``high`` (a pydantic
        ValidationError from ``write`` is ``error:3``); a saved value is applied now."""
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
