"""The trajectory pieces the step generator hands a backend (Klipper's trapq, host half)
describe exactly the path it executes, through blocks, feed holds across block boundaries,
resumes and halts."""

from __future__ import annotations

import random

from server.backends.null import NullBackend
from server.machine.parts import planner_settings
from server.motion.backend import Piece
from server.motion.motion_state import HoldState
from server.motion.moves import Move, MoveKind
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from tests.conftest import make_config
from tests.integration.test_stepgen import Quiet, Ticker


class Recording(NullBackend):
    """Keeps every piece and the position the step generator published at every tick."""

    wants_trajectory = True

    def __init__(self) -> None:
        super().__init__()
        self.pieces: list[Piece] = []
        self.samples: list[tuple[float, tuple[float, ...]]] = []

    def trajectory(self, piece: Piece) -> None:
        self.pieces.append(piece)

    def sample(self, time_s: float, position_mm: object, speed_mm_s: float) -> None:
        assert isinstance(position_mm, tuple)
        self.samples.append((time_s, position_mm))


def position_from_pieces(pieces: list[Piece], time_s: float) -> tuple[float, ...] | None:
    """Where the pieces put the tool at ``time_s``: the last piece started by then rules (a
    later piece replaces the trajectory from its start), and the tool rests at its end."""
    found = None
    for piece in pieces:
        if piece.start_s <= time_s + 1e-12:
            found = piece
    if found is None:
        return None
    t = min(time_s - found.start_s, found.duration_s)
    distance = found.start_mm_s * t + 0.5 * found.accel_mm_s2 * t * t
    return tuple(s + u * distance for s, u in zip(found.start_mm, found.unit, strict=True))


def test_pieces_reproduce_every_tick_through_holds_across_short_blocks() -> None:
    core = make_config().core
    planner = Planner(planner_settings(core), (0.0, 0.0, 0.0))
    backend = Recording()
    stepgen = StepGenerator(planner, backend, (80.0, 80.0, 400.0), Quiet())
    rng = random.Random(4)
    x = y = 0.0
    for _ in range(300):
        x, y = x + rng.uniform(0.1, 0.6), y + rng.uniform(-0.01, 0.01)
        planner.append(Move((x, y + 10, 0.0), rng.choice([250.0, 300.0]), MoveKind.FEED))
    ticker = Ticker(stepgen)
    crossed = []
    for _ in range(3):
        ticker.until(lambda: stepgen.state.speed_mm_s >= 200 or stepgen.idle)
        if stepgen.idle:
            break
        before = stepgen.state.blocks_done
        stepgen.hold()
        ticker.until(lambda: stepgen.state.hold is HoldState.STOPPED)
        crossed.append(stepgen.state.blocks_done - before)
        stepgen.resume()
    ticker.until(lambda: stepgen.idle)
    checked = 0
    for time_s, position in backend.samples:
        expected = position_from_pieces(backend.pieces, time_s)
        if expected is None:
            continue
        assert max(abs(a - b) for a, b in zip(expected, position, strict=True)) < 1e-6
        checked += 1
    for index in range(1, len(backend.pieces)):  # no jump between pieces, even inside a tick
        piece = backend.pieces[index]
        before = position_from_pieces(backend.pieces[:index], piece.start_s)
        assert before is not None
        assert max(abs(a - b) for a, b in zip(before, piece.start_mm, strict=True)) < 1e-6, index
    assert checked > 500 and len(crossed) == 3 and min(crossed) >= 2, crossed
    assert stepgen.state.position_mm == (x, y + 10, 0.0)


def test_a_backend_that_does_not_want_pieces_gets_none() -> None:
    core = make_config().core
    planner = Planner(planner_settings(core), (0.0, 0.0, 0.0))
    backend = Recording()
    backend.wants_trajectory = False
    stepgen = StepGenerator(planner, backend, (80.0, 80.0, 400.0), Quiet())
    planner.append(Move((10.0, 0.0, 0.0), 100.0, MoveKind.FEED))
    Ticker(stepgen).until(lambda: stepgen.idle)
    assert backend.pieces == [] and backend.samples
