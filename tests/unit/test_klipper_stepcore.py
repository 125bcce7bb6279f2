"""The compiled step core (``_stepcore.c``) is the numpy reference, exactly, and is what the
Klipper backend runs; without it the backend refuses to start, naming what to install."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server.backends.klipper import _stepcore, stepcompress, steptimes
from server.backends.klipper.stepcompress import StepCompressor
from server.backends.klipper.stepcore import MISSING
from server.backends.klipper.steptimes import Spans, step_target
from tests.conftest import DATA_ROOT, REPO
from tests.support import stepcore_reference as reference

PROPERTY = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# A stretch of step clocks: irregular gaps (tiny to huge, equal clocks included), or a
# smooth sequence (constant, accelerating or decelerating intervals) with a little jitter.
gaps = st.lists(st.one_of(st.floats(0.0, 3.0), st.floats(0.0, 5e3), st.floats(0.0, 5e7),
                          st.just(0.0)), min_size=1, max_size=30)
smooth = st.tuples(st.floats(1.0, 1e5), st.floats(-50.0, 50.0), st.integers(1, 400),
                   st.floats(0.0, 2.0), st.integers(0, 2**32))


def stretch_gaps(kind: list[float] | tuple[float, float, int, float, int]) -> list[float]:
    if isinstance(kind, list):
        return kind
    interval, add, count, jitter, seed = kind
    k = np.arange(count)
    steps = np.maximum(interval + add * k, 0.5)
    return list(steps + np.random.default_rng(seed).uniform(0.0, jitter, count))


@PROPERTY
@given(stretches=st.lists(st.one_of(gaps, smooth), min_size=1, max_size=4),
       start=st.floats(0.0, 1e6), last_clock=st.integers(0, 2**40),
       behind=st.floats(0.0, 1e4), max_error=st.one_of(st.just(0.0), st.floats(0.0, 5.0),
                                                     st.floats(0.0, 2e3), st.floats(0.0, 1e9)),
       final=st.booleans())
def test_the_compiled_compression_is_the_reference_exactly(
    stretches: list[list[float] | tuple[float, float, int, float, int]], start: float,
    last_clock: int, behind: float, max_error: float, final: bool,
) -> None:
    steps = np.concatenate([stretch_gaps(kind) for kind in stretches])
    points = last_clock + start + np.cumsum(steps)
    last_exact = float(last_clock) - behind
    compressor = StepCompressor(max_error, last_clock, last_exact)
    errors: list[np.ndarray] = []
    runs, done = compressor.compress(points, final, errors)
    expected = reference.compress(points, last_clock, last_exact, max_error, final)
    assert (runs, done, compressor.last_clock, compressor.last_exact) == expected[:4]
    assert np.array_equal(np.concatenate(errors or [np.empty(0)]), expected[4])


def test_a_run_grows_to_65535_steps_as_the_reference_does() -> None:
    """Past the first window (1,024 steps) the window grows to the longest run there is."""
    k = np.arange(150_000, dtype=np.float64)
    points = 5e6 + np.cumsum(3000.0 + 0.3 * np.sin(k))  # a cruise, a little jitter
    for final in (True, False):
        compressor = StepCompressor(40.0, 4_000_000, 4e6)
        runs, done = compressor.compress(points, final)
        expected = reference.compress(points, 4_000_000, 4e6, 40.0, final)
        assert (runs, done, compressor.last_clock, compressor.last_exact) == expected[:4]
        assert max(run.count for run in runs) == 65535


Row = tuple[float, float, float, float, float, float, int, float]
pieces = st.tuples(
    st.sampled_from([80.0, -80.0, 56.6, -13.0, 400.0, 0.7, -3200.0]),  # u, steps/mm (signed)
    st.sampled_from([(0.0, 2000.0), (60.0, 0.0), (60.0, -1500.0), (5.0, 300.0), (0.0, 0.0),
                     (100.0, -2e5), (1e-3, 1.0)]),  # v0, a
    st.floats(1e-6, 0.05), st.floats(-0.49, 0.49))


@PROPERTY
@given(spans=st.lists(pieces, min_size=1, max_size=40),
       to_clock=st.one_of(st.just((0.0, 1.0, 0.0)),
                          st.tuples(st.floats(0.0, 2**40), st.floats(1e6, 5e8),
                                    st.floats(0.0, 1e5))))
def test_the_compiled_step_times_are_the_reference_exactly(
    spans: list[tuple[float, tuple[float, float], float, float]],
    to_clock: tuple[float, float, float],
) -> None:
    """Pieces of every kind one after another: reversals, standstills, a deceleration past
    its stop (rounding), pieces of no step; in print time or mapped to MCU clocks."""
    solved, position, base_s = Spans(), 0, 100.0
    for u, (v0, a), duration_s, offset in spans:
        x0 = position + offset
        target = step_target(x0 + u * (v0 * duration_s + 0.5 * a * duration_s * duration_s))
        if target != position:
            solved.add(x0, u, v0, a, duration_s, position, target, base_s)
        position, base_s = target, base_s + duration_s
    times = solved.solve(to_clock)
    expected = reference.solve(solved.rows, solved.counts, *to_clock)
    assert len(times) == sum(solved.counts) and np.array_equal(times, expected)
    assert np.all(np.diff(times) >= 0.0)


def test_the_backend_runs_the_compiled_core_and_no_numpy_fallback() -> None:
    assert Path(_stepcore.__file__ or "").suffix in (".so", ".pyd")
    assert stepcompress.compress is _stepcore.compress and steptimes.solve is _stepcore.solve
    assert inspect.isbuiltin(stepcompress.compress) and inspect.isbuiltin(steptimes.solve)
    for name in ("windows", "longest_run", "best_run", "_times"):
        assert not hasattr(stepcompress, name) and not hasattr(steptimes, name)


KLIPPER_TOML = """\
[axes.x]
steps_per_mm = 80
max_rate_mm_s = 500
accel_mm_s2 = 3000
max_mm = 400
[axes.y]
steps_per_mm = 80
max_rate_mm_s = 500
accel_mm_s2 = 3000
max_mm = 300
[backend]
kind = "klipper"
serial = "/dev/ttyACM0"
[backend.axes.x]
step_pin = "PB13"
dir_pin = "PB12"
[backend.axes.y]
step_pin = "PB10"
dir_pin = "PB2"
"""


def motiond(args: list[str], without_core: bool) -> subprocess.CompletedProcess[str]:
    """``motiond args`` in a fresh interpreter, where importing the core fails if asked."""
    block = "sys.modules['server.backends.klipper._stepcore'] = None; " if without_core else ""
    code = f"import sys; {block}from server.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], cwd=REPO, capture_output=True,
                          text=True, timeout=60)


def test_without_the_compiled_core_the_klipper_backend_refuses_naming_what_to_install() -> None:
    path = DATA_ROOT / "klipper-no-core.toml"
    path.write_text(KLIPPER_TOML)
    check = ["check-config", str(path)]
    assert motiond(check, without_core=False).returncode == 0  # the config itself is fine
    result = motiond(check, without_core=True)
    assert result.returncode == 1 and MISSING in result.stderr.splitlines()
    serve = ["--config", str(path), "--data-dir", str(DATA_ROOT / "no-core"), "--tcp-port", "0",
             "--http-port", "0"]
    result = motiond(serve, without_core=True)  # refused before it opens anything
    assert result.returncode == 2 and MISSING in result.stderr.splitlines()
    assert "sudo apt install gcc python3-dev, then pip install -e . again" in MISSING
