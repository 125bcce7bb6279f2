"""G-code text for a laser in Grbl's laser mode, written as LightBurn writes it for Grbl.

M4 (dynamic power: the power follows the speed, so corners do not burn darker) with S the
layer's power; G0 travels with the laser off (a rapid never fires in laser mode); G1 cuts, or
moves with ``S0`` where the head must keep its speed with the laser off (overscan, short
white runs). Coordinates are absolute mm, three decimals; F is mm/min. The program ends with
M5.
"""

from __future__ import annotations

import numpy as np

from server.cam.model import Points


def _n(value: float) -> str:
    text = f"{value:.3f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


class Program:
    """The lines of a job, with the modal state it has set (so nothing is repeated)."""

    def __init__(self, name: str, max_s: float) -> None:
        self.lines = [f"; {name}: made by motiond import", "G21 G90 G94", "M5 S0"]
        self.max_s = max_s
        self._s: int | None = None
        self._f: float | None = None
        self._at: tuple[float, float] | None = None
        self._feed = 1000.0

    def comment(self, text: str) -> None:
        self.lines.append(f"; {text}")

    def start_layer(self, speed_mm_min: float) -> None:
        """M4 for what follows, at ``speed_mm_min``; the power is set by each cut."""
        self.lines.append("M4 S0")
        self._s, self._f = 0, None
        self._feed = speed_mm_min

    def position(self) -> tuple[float, float]:
        """Where the head is after the lines so far (machine zero before the first move)."""
        return self._at or (0.0, 0.0)

    def s_value(self, power_pct: float) -> int:
        return round(self.max_s * power_pct / 100.0)

    def travel(self, x: float, y: float) -> None:
        if self._at is not None and abs(self._at[0] - x) < 5e-4 and abs(self._at[1] - y) < 5e-4:
            return
        self.lines.append(f"G0 X{_n(x)} Y{_n(y)}")
        self._at = (x, y)

    def polyline(self, points: Points, power_pct: float) -> None:
        """Travel to the first point, cut through the rest at one power."""
        self.travel(float(points[0, 0]), float(points[0, 1]))
        s = self.s_value(power_pct)
        words = self._modal(s)
        cuts = [f"G1 X{x} Y{y}" for x, y in np.round(points[1:], 3).tolist()]
        if cuts:
            cuts[0] += words
            self.lines += cuts
            self._at = (float(points[-1, 0]), float(points[-1, 1]))

    def cut_to(self, x: float, y: float, power_pct: float) -> None:
        """One G1 from where the head is (``power_pct`` 0: moving on with the laser off)."""
        self.lines.append(f"G1 X{_n(x)} Y{_n(y)}{self._modal(self.s_value(power_pct))}")
        self._at = (x, y)

    def moves_x(self, moves: list[tuple[float, int]], y: float) -> None:
        """G1 along X (the head's Y stays ``y``) to each x at its S value (0: laser off)."""
        lines = self.lines
        feed = f" F{_n(self._feed)}" if self._f != self._feed else ""
        self._f = self._feed
        s_now = self._s
        for x, s in moves:
            if s != s_now:
                lines.append(f"G1 X{round(x, 3)} S{s}{feed}")
                s_now = s
            else:
                lines.append(f"G1 X{round(x, 3)}{feed}")
            feed = ""
        self._s = s_now
        if moves:
            self._at = (moves[-1][0], y)

    def _modal(self, s: int) -> str:
        words = ""
        if s != self._s:
            words += f" S{s}"
            self._s = s
        if self._f != self._feed:
            words += f" F{_n(self._feed)}"
            self._f = self._feed
        return words

    def finish(self) -> str:
        self.lines.append("M5 S0")
        return "\n".join(self.lines) + "\n"
