"""Step times to ``queue_step`` runs within a bounded error (pure).

The MCU executes ``queue_step interval count add`` as Klipper's src/stepper.c does: from the
stepper's last step clock ``L``, step ``k`` (0-based) happens at
``L + (k+1)·interval + add·k·(k+1)/2``. A run is valid when every step lands inside its window
``[exact - err, exact]`` (never late, at most ``max_error`` early, and never more than half the
gap to the previous step early, so steps keep their order). For a candidate ``add`` the windows
bound ``interval`` from both sides; a running max/min over the windows gives the longest run
that ``add`` allows. The ``add`` is searched as Klipper's stepcompress does: a run that ends
because its next step would come too early wants a larger ``add``, one whose next step would
come too late a smaller one; the range narrows by a quarter each try and never beyond what the
error bound allows two quadratic sequences of that length to differ by
(``(6 + 4√2)·max_error / count²``). The run reaching furthest wins, and a run without ``add``
(a shorter message) wins when it covers nearly as many steps. Runs grow up to 65,535 steps: the
window considered grows while the best run fills it.

The algorithm runs compiled (``_stepcore.c``, :func:`compress`): a run costs a few
microseconds, not dozens of numpy calls. The backend's steppers compress through it from C
(``_stepaxis.c``: :class:`~.stepcore.StepAxis`); :class:`StepCompressor` is its face for the
tests and tools. ``tests/support/stepcore_reference.py`` holds it in numpy, the oracle the
tests hold the compiled core to, exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from server.backends.klipper.stepcore import (
    ADD_MAX,
    ADD_MIN,
    MAX_COUNT,
    MAX_TRIES,
    QUADRATIC_DEV,
    WINDOW,
    compress,
)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

# The constants are the compiled core's: MAX_COUNT (65,535) steps a run at most, ADD_MIN..ADD_MAX
# (-32,768..32,767) the add, WINDOW (1,024) steps considered for one run at first (grown while a
# run fills it), QUADRATIC_DEV (11: 6 + 4√2 rounded down, as Klipper uses), MAX_TRIES (48) adds.
__all__ = ["ADD_MAX", "ADD_MIN", "MAX_COUNT", "MAX_TRIES", "QUADRATIC_DEV", "WINDOW",
           "StepCompressor", "StepRun", "run_clocks"]


@dataclass(frozen=True, slots=True)
class StepRun:
    """One ``queue_step``: ``count`` steps, first ``interval`` ticks after the last, +``add``."""

    interval: int
    count: int
    add: int


def run_clocks(last_clock: int, run: StepRun) -> IntArray:
    """The MCU clock of every step of ``run`` after a last step at ``last_clock``."""
    k = np.arange(run.count, dtype=np.int64)
    return last_clock + (k + 1) * run.interval + run.add * (k * (k + 1) // 2)


@dataclass(slots=True)
class StepCompressor:
    """Per-stepper compression state: the last step's MCU clock and exact time."""

    max_error: float  # ticks
    last_clock: int = 0
    last_exact: float = 0.0

    def compress(self, points: FloatArray, final: bool,
                 errors: list[FloatArray] | None = None) -> tuple[list[StepRun], int]:
        """Runs for a prefix of ``points`` (exact step clocks, one direction, ascending) and how
        many points they cover. Unless ``final``, a last run that reaches the end of ``points``
        is held back (more steps may extend it). With ``errors``, how early each covered step
        is (ticks, one array) is appended to it."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        early = np.empty(len(points)) if errors is not None else None
        raw, done, self.last_clock, self.last_exact = compress(
            points, self.last_clock, self.last_exact, self.max_error, final, early)
        if early is not None and errors is not None and done:
            errors.append(early[:done])
        return [StepRun(*run) for run in raw], done
