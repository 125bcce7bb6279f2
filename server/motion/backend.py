"""The backend interface: where the step generator's steps and the tools' outputs go.

A backend is called from the event loop at every tick; every method must return in
microseconds and never block. Units: steps are whole numbers per axis relative to the previous
call; times are seconds on the kernel's clock; outputs are duty cycles in [0, 1].
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True, slots=True)
class PowerLaw:
    """The tool's duty along a piece as a function of the speed (a laser's power following the
    speed, Grbl's M4): ``min(ceiling, max(0, offset + per_mm_s · speed))``."""

    offset: float
    per_mm_s: float = 0.0
    ceiling: float = 1.0

    def at(self, speed_mm_s: float) -> float:
        return min(self.ceiling, max(0.0, self.offset + self.per_mm_s * speed_mm_s))


@dataclass(frozen=True, slots=True)
class Piece:
    """A stretch of trajectory at constant acceleration along a straight line (Klipper's trapq).

    Position at ``start_s + t`` (``0 <= t <= duration_s``) is
    ``start_mm + unit * (start_mm_s * t + accel_mm_s2 * t² / 2)``. A piece replaces whatever
    trajectory an earlier piece described from ``start_s`` on (a feed hold cuts a block short).
    ``power``: the duty of the output that follows motion (``follow_power``) along the piece,
    None where it is off (rapids, a feed hold's deceleration, no tool on).
    """

    start_s: float
    duration_s: float
    start_mm: tuple[float, ...]
    unit: tuple[float, ...]
    start_mm_s: float
    accel_mm_s2: float
    power: PowerLaw | None = None

    def lasting(self, duration_s: float) -> Piece:
        """The same piece, ``duration_s`` long (cut short, or lengthened by the blocks that
        continue it): a constructor call, not :func:`dataclasses.replace`'s look at the fields,
        several times a tick."""
        return Piece(self.start_s, duration_s, self.start_mm, self.unit, self.start_mm_s,
                     self.accel_mm_s2, self.power)


class Backend(Protocol):
    """What a hardware or simulated machine must provide.

    A backend whose ``sample()`` has nothing to do while nothing moves says
    ``ticks_when_idle = False`` (as :class:`NoHardware` does; Klipper's says so whenever it has
    nothing queued, on or to report): the step generator then sleeps, until the machine has work
    or the backend calls the function given to :meth:`wake_with`. Without the attribute, it is
    ticked at ``tick_hz`` always. Before it sleeps, the machine calls the backend's ``rest()``
    if it has one (Klipper's reads its MCU at the samples while they come, and as data arrives
    once they stop).

    A backend that times its own steps from the pieces may set ``tick_s``: the step generator
    then ticks that often instead of at ``tick_hz`` (Klipper's: every flush; steps, actions and
    the laser's power are timed from the pieces, not from the ticks), and may say with
    ``next_sample_s(time_s)`` when it needs the sample after the one at ``time_s``: while
    motion needs nothing of the ticks themselves, the step generator ticks then if later;
    such sparse ticks each cover many blocks, so it may also set ``blocks_per_call``, how many
    one call of the step generator goes through before the rest is sliced (default 64).
    One that has ``follow_power(name, period_s)`` returning True drives the output ``name``
    from each piece's ``power`` itself, at most every ``period_s`` (the laser module then
    stops sampling).
    """

    wants_trajectory: bool
    """Whether :meth:`trajectory` is used (the step generator builds no pieces otherwise)."""

    def step(self, time_s: float, delta_steps: Sequence[int]) -> None:
        """Move each axis by ``delta_steps[i]`` whole steps (signed), completed by ``time_s``."""
        ...

    def trajectory(self, piece: Piece) -> None:
        """The exact path motion takes next (hardware that times its own steps); may ignore."""
        ...

    def sample(self, time_s: float, position_mm: Sequence[float], speed_mm_s: float) -> None:
        """Record the tool's state at a tick (for traces and history; may do nothing)."""
        ...

    def set_output(self, name: str, value: float, time_s: float) -> None:
        """Set an output pin (laser PWM, spindle, fan) to a duty cycle in [0, 1]."""
        ...

    def motors(self, enabled: bool, time_s: float) -> None:
        """Stepper drivers on or off (M17, M18/M84, ``$SLP``) when motion reaches ``time_s``;
        hardware turns them on again by itself before the next step."""
        ...

    def declare_tool(self, name: str) -> None:
        """The output ``name`` drives the tool (laser, spindle): traces record it as power."""
        ...

    def output(self, name: str) -> float:
        """The last value set on an output (0.0 if never set)."""
        ...

    def probe_triggered(self, position_mm: Sequence[float]) -> bool:
        """Whether the probe input is active with the tool at ``position_mm``."""
        ...

    def switch_triggered(self, name: str) -> bool:
        """Whether the named switch (``x_min``...) is active now, where the tool really is."""
        ...

    def place_switch(self, name: str, at_mm: float) -> None:
        """Simulated machines: put the named switch at ``at_mm`` on its axis (others ignore)."""
        ...

    def halt(self) -> None:
        """Emergency stop: drop every queued step and turn every output off at once."""
        ...

    def done_at_s(self) -> float:
        """When (on the kernel's clock) the hardware will have carried out all the motion it
        was given: later than the step generator's end where it runs behind (a Klipper MCU
        runs a lead time later); 0.0 when nothing is pending."""
        ...

    def position_at_mm(self, time_s: float) -> Sequence[float] | None:
        """Where the tool is at ``time_s`` (now) when the hardware runs behind the step
        generator (a Klipper MCU: a lead time); None where it does not."""
        ...

    def speed_at_mm_s(self, time_s: float) -> float | None:
        """The path speed at ``time_s`` (now) when the hardware runs behind the step
        generator; None where it does not."""
        ...

    async def recover(self) -> None:
        """``$X`` / M999 after an alarm: make the hardware usable again (a Klipper MCU that
        shut down is restarted and configured); CommandError while it cannot be."""
        ...

    def watch_position(self, relocate: Callable[[Sequence[float]], None]) -> None:
        """The machine's hook for hardware that stopped elsewhere than planned (a Klipper
        MCU's emergency stop mid-move): ``relocate`` is called with where the tool is (mm)."""
        ...

    def wake_with(self, wake: Callable[[], None]) -> None:
        """The machine's hook for a backend that needs ticks again while idle (a fault to
        report from :meth:`sample`, an output to keep refreshed): it calls ``wake``."""
        ...

    async def run(self) -> None:
        """Serve the hardware until cancelled (owned by the machine; may return at once)."""
        ...

    def close(self) -> None:
        """Release the hardware; safe to call twice."""
        ...


class NoHardware:
    """What a backend with nothing below the step generator does not need (the simulated and
    null machines): no trajectory, nothing queued to halt, no drivers, no task to run."""

    wants_trajectory = False
    ticks_when_idle = False  # nothing to watch: the step generator sleeps while idle

    def trajectory(self, piece: Piece) -> None:
        pass

    def halt(self) -> None:
        pass

    def done_at_s(self) -> float:
        return 0.0

    def position_at_mm(self, time_s: float) -> Sequence[float] | None:
        return None

    def speed_at_mm_s(self, time_s: float) -> float | None:
        return None

    async def recover(self) -> None:
        pass

    def watch_position(self, relocate: Callable[[Sequence[float]], None]) -> None:
        pass

    def motors(self, enabled: bool, time_s: float) -> None:
        pass

    def wake_with(self, wake: Callable[[], None]) -> None:
        pass

    async def run(self) -> None:
        pass
