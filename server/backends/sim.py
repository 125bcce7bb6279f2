"""The simulated machine (the default backend).

It keeps step counts per axis, the value of every output, a bounded history of
``(time_s, position_mm..., speed_mm_s, tool power)`` samples, a trace of output changes, and
optional probe and switch models: the probe triggers when the tool crosses a configured
position on one axis; a switch ``x_min``/``x_max`` triggers at or beyond a configured position.
With ``trace_csv`` set it writes every sample of the run to a CSV file when closed.
"""

from __future__ import annotations

import csv
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path

from server.motion.backend import NoHardware


class SimBackend(NoHardware):
    """A machine made of counters; see the module docstring."""

    def __init__(
        self,
        axis_names: Sequence[str],
        steps_per_mm: Sequence[float],
        *,
        history_samples: int = 100_000,
        trace_csv: Path | None = None,
        probe_at_mm: Mapping[str, float] | None = None,
        switches_at_mm: Mapping[str, float] | None = None,
    ) -> None:
        self.axis_names = tuple(axis_names)
        self.steps_per_mm = tuple(steps_per_mm)
        self.steps = [0] * len(self.axis_names)
        self.steps_travelled = 0  # every step emitted, whatever its direction
        self.history: deque[tuple[float, ...]] = deque(maxlen=history_samples or None)
        self.output_trace: list[tuple[float, str, float]] = []
        self.events: list[str] = []  # coarse log of notable calls (tests check shutdown order)
        self._outputs: dict[str, float] = {}
        self._tools: list[str] = []  # outputs whose duty is the tool power in the history
        self._probe = {self.axis_names.index(k.upper()): v for k, v in (probe_at_mm or {}).items()}
        self.switches_at_mm: dict[str, float] = dict(switches_at_mm or {})
        self._trace_csv = trace_csv
        self._trace_rows: list[tuple[float, ...]] | None = [] if trace_csv else None
        self.closed = False

    def step(self, time_s: float, delta_steps: Sequence[int]) -> None:
        steps = self.steps
        for axis, delta in enumerate(delta_steps):
            steps[axis] += delta
            self.steps_travelled += abs(delta)

    def sample(self, time_s: float, position_mm: Sequence[float], speed_mm_s: float) -> None:
        power = max((self._outputs.get(name, 0.0) for name in self._tools), default=0.0)
        row = (time_s, *position_mm, speed_mm_s, power)
        self.history.append(row)
        if self._trace_rows is not None:
            self._trace_rows.append(row)

    def set_output(self, name: str, value: float, time_s: float) -> None:
        if self._outputs.get(name) != value:
            self._outputs[name] = value
            self.output_trace.append((time_s, name, value))

    def declare_tool(self, name: str) -> None:
        if name not in self._tools:
            self._tools.append(name)

    def output(self, name: str) -> float:
        return self._outputs.get(name, 0.0)

    def position_mm(self) -> tuple[float, ...]:
        """Where the steps put the tool."""
        return tuple(s / spm for s, spm in zip(self.steps, self.steps_per_mm, strict=True))

    def set_probe(self, axis: str, at_mm: float | None) -> None:
        """Place (or remove, with None) the probe trigger on one axis."""
        index = self.axis_names.index(axis.upper())
        if at_mm is None:
            self._probe.pop(index, None)
        else:
            self._probe[index] = at_mm

    def probe_triggered(self, position_mm: Sequence[float]) -> bool:
        return any(position_mm[axis] <= at_mm + 1e-9 for axis, at_mm in self._probe.items())

    def place_switch(self, name: str, at_mm: float) -> None:
        self.switches_at_mm[name] = at_mm

    def switch_triggered(self, name: str) -> bool:
        at_mm = self.switches_at_mm.get(name)
        if at_mm is None:
            return False
        position_mm = self.position_mm()
        axis = self.axis_names.index(name[0].upper())
        if name.endswith("_min"):
            return position_mm[axis] <= at_mm + 1e-9
        return position_mm[axis] >= at_mm - 1e-9

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.events.append("close")
        if self._trace_csv is not None and self._trace_rows is not None:
            self._write_trace(self._trace_csv, self._trace_rows)

    def _write_trace(self, path: Path, rows: list[tuple[float, ...]]) -> None:
        with path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(
                ["time_s", *(f"{a.lower()}_mm" for a in self.axis_names), "speed_mm_s", "power"]
            )
            writer.writerows(rows)
