"""``motiond render``: the toolpath seen from the top, as SVG or PNG (matplotlib).

Feed moves are coloured by their planned cruise speed (with a colour bar in mm/min), rapids
are thin dashed grey lines, and laser power (S relative to the maximum S) sets the stroke
opacity of laser moves, relative to the highest S of the job. In laser mode a feed move with
the laser off (M5, or S0) is drawn as travel, as a rapid is. ``by_power`` draws the power
view instead: each cut in grey by its S (black none, white the job's highest), as a raster
will burn.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.motion.moves import MoveKind, ToolMode
from server.motion.planner import Block


@dataclass(slots=True)
class Toolpath:
    """Segments gathered from planned blocks, in the XY plane (mm)."""

    feed: list[tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=list)
    speed_mm_s: list[float] = field(default_factory=list)
    power: list[float] = field(default_factory=list)
    rapid: list[tuple[tuple[float, float], tuple[float, float]]] = field(default_factory=list)

    def add(self, block: Block, laser_mode: bool) -> None:
        move = block.move
        if move is None or block.length_mm == 0.0:
            return
        segment = ((block.start_mm[0], block.start_mm[1]), (block.end_mm[0], block.end_mm[1]))
        on = move.tool_mode is not ToolMode.OFF
        travel = move.kind in (MoveKind.RAPID, MoveKind.JOG, MoveKind.HOMING)
        if travel or (laser_mode and (not on or move.s_value <= 0)):
            self.rapid.append(segment)
            return
        self.feed.append(segment)
        self.speed_mm_s.append(block.cruise_mm_s)
        self.power.append(move.s_value if (laser_mode and on) else -1.0)

    def relative_power(self) -> list[float]:
        """Power per feed segment in [0, 1] relative to the job's highest S (1 when not a laser)."""
        top = max(self.power, default=0.0)
        return [1.0 if power < 0 or top <= 0 else power / top for power in self.power]


def collect(blocks: Iterable[Block], laser_mode: bool) -> Toolpath:
    path = Toolpath()
    for block in blocks:
        path.add(block, laser_mode)
    return path


def draw(path: Toolpath, output: Path, title: str, *, by_power: bool = False) -> None:
    """Write the picture; the format follows the file suffix (.svg or .png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    figure, axes = plt.subplots(figsize=(10, 8), dpi=120)
    if path.rapid:
        axes.add_collection(
            LineCollection(
                path.rapid, colors="#9a9a9a", linewidths=0.5, linestyles=(0, (3, 3)),
                label="travel (rapid, laser off)",
            )
        )
    colours, mappable, label = _colours(path, by_power)
    axes.add_collection(LineCollection(path.feed, colors=colours, linewidths=0.9))
    colour_bar = figure.colorbar(mappable, ax=axes, shrink=0.8)
    colour_bar.set_label(label)
    axes.autoscale()
    axes.set_aspect("equal")
    axes.set_xlabel("X (mm)")
    axes.set_ylabel("Y (mm)")
    axes.set_title(title)
    axes.grid(True, linewidth=0.3, alpha=0.5)
    if path.rapid:
        axes.legend(loc="upper right", fontsize="small")
    figure.tight_layout()
    figure.savefig(output)
    plt.close(figure)


def _colours(path: Toolpath, by_power: bool) -> tuple[list[Any], Any, str]:
    """Per feed segment: its colour, the colour bar's mappable and its label."""
    import matplotlib
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    if by_power:  # grey by S on white: the darker, the more it burns
        greys = matplotlib.colormaps["Greys"]
        power = path.relative_power()
        mappable = plt.cm.ScalarMappable(norm=Normalize(0.0, 1.0), cmap=greys)
        return [greys(0.15 + 0.85 * p) for p in power], mappable, "laser power (S / highest S)"
    speeds_mm_min = [speed * 60.0 for speed in path.speed_mm_s]
    low, high = min(speeds_mm_min, default=0.0), max(speeds_mm_min, default=1.0)
    if high - low < 1.0:  # one speed all through: give the colour bar a readable span
        low, high = max(0.0, low - 50.0), high + 50.0
    norm = Normalize(vmin=low, vmax=high)
    colormap = matplotlib.colormaps["viridis"]
    colours = [
        (*colormap(norm(speed))[:3], 0.1 + 0.9 * power)
        for speed, power in zip(speeds_mm_min, path.relative_power(), strict=True)
    ]
    return colours, plt.cm.ScalarMappable(norm=norm, cmap=colormap), "planned speed (mm/min)"
