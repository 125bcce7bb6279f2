"""A backend that discards everything (benchmarks, check runs)."""

from __future__ import annotations

from collections.abc import Sequence

from server.motion.backend import NoHardware


class NullBackend(NoHardware):
    """Discards steps and samples; remembers outputs so tools can be checked off."""

    def __init__(self) -> None:
        self._outputs: dict[str, float] = {}

    def step(self, time_s: float, delta_steps: Sequence[int]) -> None:
        pass

    def sample(self, time_s: float, position_mm: Sequence[float], speed_mm_s: float) -> None:
        pass

    def set_output(self, name: str, value: float, time_s: float) -> None:
        self._outputs[name] = value

    def declare_tool(self, name: str) -> None:
        pass

    def output(self, name: str) -> float:
        return self._outputs.get(name, 0.0)

    def probe_triggered(self, position_mm: Sequence[float]) -> bool:
        return False

    def switch_triggered(self, name: str) -> bool:
        return False

    def place_switch(self, name: str, at_mm: float) -> None:
        pass

    def close(self) -> None:
        pass
