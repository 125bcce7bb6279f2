"""The planner's block columns: compacting the window keeps its values and copies it once."""

from __future__ import annotations

import tracemalloc

import numpy as np

from server.motion.block import BlockColumns

ROWS, INPUT_ROWS = 20, [0, 1, 2, 5, 6]


def filled(capacity: int, window: int) -> BlockColumns:
    """Columns whose window (``window`` blocks) has drifted to the end of the array."""
    columns = BlockColumns(ROWS, INPUT_ROWS, read_rows=4, capacity=capacity, sync_every=64)
    for i in range(capacity):
        columns.push(tuple(float(i * 10 + r) for r in range(len(INPUT_ROWS))))
        if columns.tail - columns.head > window:
            columns.sync()
            columns.pop_front()
    columns.sync()
    return columns


def test_compacting_keeps_every_value_of_the_window() -> None:
    columns = filled(4096, 1500)
    before = columns.window().copy()
    columns.push((1.0, 2.0, 3.0, 4.0, 5.0))  # past the end: the window moves to the front
    columns.sync()
    assert columns.head == 0 and columns.data.shape[1] == 4096, "moved, not grown"
    assert np.array_equal(columns.window()[:, :-1], before)
    assert columns.window()[INPUT_ROWS, -1].tolist() == [1.0, 2.0, 3.0, 4.0, 5.0]


def test_compacting_makes_no_temporary_copy_of_the_window() -> None:
    """numpy copies an assignment between overlapping-looking 2-D views through a temporary:
    a window of 1,500 blocks x 20 rows is 240 kB more, and its page faults cost ~0.3 ms."""
    columns = filled(4096, 1500)
    window_bytes = columns.window().nbytes
    tracemalloc.start()
    try:
        columns.push((1.0, 2.0, 3.0, 4.0, 5.0))
        columns.sync()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert columns.head == 0
    assert peak < window_bytes / 4, f"{peak:,} bytes allocated moving {window_bytes:,}"
