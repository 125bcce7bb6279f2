"""The compiled step core (``_stepcore.c``); see :mod:`.stepcore`."""

import numpy as np
import numpy.typing as npt

MAX_COUNT: int
ADD_MIN: int
ADD_MAX: int
WINDOW: int
QUADRATIC_DEV: int
MAX_TRIES: int

def compress(
    points: npt.NDArray[np.float64], last_clock: int, last_exact: float, max_error: float,
    final: bool, errors: npt.NDArray[np.float64] | None, /,
) -> tuple[list[tuple[int, int, int]], int, int, float]: ...
def solve(
    rows: list[tuple[float, float, float, float, float, float, float, float]],
    counts: list[int], out: npt.NDArray[np.float64], ref_clock: float, hz: float,
    ref_s: float, /,
) -> int: ...
def message(prefix: bytes, count: int, /, *values: int) -> bytes: ...
def crc16(data: bytes, /) -> int: ...
def frame(head: int, payload: bytes, /) -> bytes: ...
def step_messages(
    prefix: bytes, oid: int, runs: list[tuple[int, int, int]], last_clock: int, /,
) -> tuple[list[tuple[bytes, int, int]], int]: ...
