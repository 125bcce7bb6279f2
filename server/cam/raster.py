"""Images: gray levels to power, line by line, as a raster engrave.

The image is resampled to one pixel per ``interval_mm`` both ways (Pillow's box filter, so
each new pixel is the mean of what it covers). ``dither="grayscale"`` maps each pixel's
darkness onto ``min_power_pct .. power_pct`` (white is off); the others make each pixel on
or off at ``power_pct``: a threshold at half, or error diffusion (Floyd–Steinberg, Jarvis–
Judice–Ninke, Stucki). Along each line, neighbouring pixels of one S become one G1; the head
starts ``overscan_mm`` before the first burnt pixel and runs on as far past the last (G1 S0),
so every pixel is burnt at full speed; a white run longer than twice the overscan is crossed
with G0. Lines alternate direction when ``bidirectional``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from server.cam.emit import Program
from server.cam.model import LayerSettings, Raster
from server.errors import DrawingError

MAX_PIXELS = 25_000_000  # after resampling to the line interval: 500 x 500 mm at 0.1 mm
WHITE = 0.998  # gray above this is not burnt

KERNELS: dict[str, tuple[float, list[tuple[int, int, float]]]] = {
    # (divisor, [(row offset, column offset, weight)])
    "floyd-steinberg": (16.0, [(0, 1, 7), (1, -1, 3), (1, 0, 5), (1, 1, 1)]),
    "jarvis": (48.0, [(0, 1, 7), (0, 2, 5), (1, -2, 3), (1, -1, 5), (1, 0, 7), (1, 1, 5),
                      (1, 2, 3), (2, -2, 1), (2, -1, 3), (2, 0, 5), (2, 1, 3), (2, 2, 1)]),
    "stucki": (42.0, [(0, 1, 8), (0, 2, 4), (1, -2, 2), (1, -1, 4), (1, 0, 8), (1, 1, 4),
                      (1, 2, 2), (2, -2, 1), (2, -1, 2), (2, 0, 4), (2, 1, 2), (2, 2, 1)]),
}


def resampled(raster: Raster, interval_mm: float) -> npt.NDArray[np.float32]:
    """The gray levels at one pixel per ``interval_mm`` (rows from the top)."""
    from PIL import Image

    columns = max(1, round(raster.width_mm / interval_mm))
    rows = max(1, round(raster.height_mm / interval_mm))
    if columns * rows > MAX_PIXELS:
        raise DrawingError(
            f"image: {columns:,} x {rows:,} lines at {interval_mm} mm is over {MAX_PIXELS:,} "
            "pixels: a coarser interval or a smaller size")
    image = Image.fromarray(raster.gray.astype(np.float32), mode="F")
    if image.size != (columns, rows):
        image = image.resize((columns, rows), Image.Resampling.BOX)
    return np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0)


def power_levels(gray: npt.NDArray[np.float32], settings: LayerSettings) -> np.ndarray:
    """Power in percent per pixel (0: off)."""
    darkness = 1.0 - gray
    if settings.dither == "grayscale":
        span = settings.power_pct - settings.min_power_pct
        power = settings.min_power_pct + span * darkness
        return np.where(gray >= WHITE, 0.0, power)
    on = darkness >= 0.5 if settings.dither == "threshold" else diffuse(darkness, settings.dither)
    return np.where(on, settings.power_pct, 0.0)


def diffuse(darkness: np.ndarray, method: str) -> npt.NDArray[np.bool_]:
    """Error diffusion: each pixel on or off, its error spread over the pixels not yet done.
    Within a line the spread is sequential (a Python loop over two carries); onto the lines
    below it is one numpy convolution per line."""
    divisor, weights = KERNELS[method]
    rows, columns = darkness.shape
    work = np.zeros((rows + 2, columns + 4), dtype=np.float64)
    work[:rows, 2:columns + 2] = darkness
    on = np.zeros((rows, columns), dtype=bool)
    same_row = {dx: w / divisor for dy, dx, w in weights if dy == 0}
    w1, w2 = same_row.get(1, 0.0), same_row.get(2, 0.0)
    below = {dy: np.zeros(5) for dy in (1, 2)}
    for dy, dx, w in weights:
        if dy:
            below[dy][2 + dx] = w / divisor  # pixel c's error reaches work column c + 2 + dx
    for row in range(rows):
        values = work[row, 2:columns + 2].tolist()
        errors = [0.0] * columns
        bits = [False] * columns
        carry1 = carry2 = 0.0
        for column, value in enumerate(values):
            value += carry1
            bit = value >= 0.5
            error = value - (1.0 if bit else 0.0)
            bits[column], errors[column] = bit, error
            carry1, carry2 = carry2 + w1 * error, w2 * error
        on[row] = bits
        spread = np.asarray(errors)
        for dy, kernel in below.items():
            work[row + dy, :] += np.convolve(spread, kernel, mode="full")[: columns + 4]
    return on


def engrave(program: Program, raster: Raster, settings: LayerSettings) -> None:
    """The image's lines into ``program``."""
    gray = resampled(raster, settings.interval_mm)
    s_values = np.rint(program.max_s * power_levels(gray, settings) / 100.0).astype(np.int64)
    pitch = raster.width_mm / gray.shape[1]
    edges = (raster.x_mm + pitch * np.arange(gray.shape[1] + 1)).tolist()
    forward = True
    for row in range(gray.shape[0]):
        line = s_values[row]
        burnt = np.flatnonzero(line)
        if not len(burnt):
            continue
        y = raster.y_mm + raster.height_mm - (row + 0.5) * raster.height_mm / gray.shape[0]
        _line(program, line, edges, y, settings.overscan_mm, forward)
        forward = not forward if settings.bidirectional else True


def _line(program: Program, line: np.ndarray, edges: list[float], y: float,
          overscan_mm: float, forward: bool) -> None:
    """One image line: runs of one S from the first burnt pixel to the last."""
    burnt = np.flatnonzero(line)
    first = int(burnt[0])
    values = line[first:int(burnt[-1]) + 1]
    change = np.flatnonzero(np.diff(values)) + 1
    starts = (np.concatenate([[0], change]) + first).tolist()
    ends = (np.concatenate([change, [len(values)]]) + first).tolist()
    levels = values[np.asarray(starts) - first].tolist()
    if not forward:
        starts, ends, levels = ends[::-1], starts[::-1], levels[::-1]
    sign = 1.0 if forward else -1.0
    program.travel(edges[starts[0]] - sign * overscan_mm, y)
    moves: list[tuple[float, int]] = [(edges[starts[0]], 0)]
    for start, end, level in zip(starts, ends, levels, strict=True):
        if level == 0 and abs(edges[end] - edges[start]) > 2.0 * overscan_mm + 1.0:
            moves.append((edges[start] + sign * overscan_mm, 0))
            program.moves_x(moves, y)
            program.travel(edges[end] - sign * overscan_mm, y)
            moves = [(edges[end], 0)]
        else:
            moves.append((edges[end], level))
    moves.append((edges[ends[-1]] + sign * overscan_mm, 0))
    program.moves_x(moves, y)
