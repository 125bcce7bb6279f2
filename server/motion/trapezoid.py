"""Speed planning of a window of blocks: junction limits, look-ahead passes and trapezoids.

Pure functions, no state. A window holds ``n`` blocks; *nodes* ``i = 0..n`` are the boundaries
between them (node ``i`` is the entry of block ``i``, node ``n`` the end of the window, where
motion stops). Per block ``k`` the inputs are its length ``d_k`` (mm), acceleration ``a_k``
(mm/s²), nominal speed (mm/s), junction limit ``J_k`` on the square of its entry speed
(mm²/s², the junction-deviation limit against block ``k-1``; ignored for ``k = 0`` whose entry
is fixed to the start speed) and lead time (s). Zero-length blocks use ``d = 0`` with any
positive ``a`` and a huge nominal speed.

The passes work on squared speeds, where a full-rate ramp over block ``k`` changes ``v²`` by
``2·a_k·d_k``. With ``C[i] = Σ_{k<i} 2·a_k·d_k`` and node caps ``L[i]`` (junction limit and both
neighbours' nominal speeds; 0 at the end of the window):

* backward pass (can still stop in time): ``B[i] = min_{j≥i}(L[j] + C[j]) − C[i]``, a reversed
  cumulative minimum;
* forward pass (can get there from the fixed start ``s``): ``F[i] = min_{j≤i}(V[j] − C[j]) +
  C[i]`` with ``V = max(B, s − C)`` and ``V[0] = s``.

``s − C`` is the full-rate deceleration from the start speed. It only exceeds ``B`` when the
start speed is already above what the caps allow (an override lowered the nominal speeds under a
block in motion): acceleration limits then win over the caps, which are exceeded for as short a
distance as physics allows. ``F`` is feasible both ways (``|F[i+1] − F[i]| ≤ 2·a_i·d_i``), so
every block's ramps fit in its length. Since ``B[0]`` is the fastest feasible start, ``s − C``
is only applied when ``s > B[0]`` (by more than rounding, :data:`OVER_SPEED`): a start speed
carried from an earlier plan, a rounding above ``B[0]``, would otherwise leave the window's end
at a speed of a rounding's square root (1e-7 mm/s) instead of a stop.

Rounding: the prefix form carries an absolute error in ``v²`` of a few ulps of ``C[n]`` (250 mm
of window at 1,000 mm/s² gives ``C[n] = 5e5`` mm²/s², so about 1e-10 mm²/s²). Clamping with
``B ≤ L`` and ``F ≤ V``, which hold exactly in real arithmetic, makes every speed that is set by
its own cap exact, and stops (caps of 0) are exact anyway.

:func:`plan_window` does this with a handful of numpy operations over the whole window, and
:func:`plan_prefix` over its first blocks only, the rest entering through one number;
:func:`plan_window_reference` is the same computation written as the classic per-block loops,
kept as the readable specification (tests check they agree; the benchmark times both).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from operator import mul

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

PROFILE_ROWS = 7
"""Rows of the plan: entry, cruise, exit speed (mm/s); ramp1, flat, ramp2, total time (s)."""
STILL_LIMIT = 1e150
"""Speed and acceleration limit of a zero-length block (see :func:`axis_limits`)."""
OVER_SPEED = 1.0 + 1e-9
"""A start speed (squared) above the window's backward limit by more than this factor is an
over-speed start; below it, the difference is the rounding of a speed carried from an
earlier plan (its square root, squared again)."""
"""Speed and acceleration limit of a zero-length block (see :func:`axis_limits`)."""


def junction_speed_sq(
    prev_unit: Sequence[float], unit: Sequence[float], accel_mm_s2: float, deviation_mm: float
) -> float:
    """The junction-deviation limit on v² (mm²/s²) between two directions (Grbl/Smoothie).

    ``v² = a·δ·sin(θ/2)/(1 − sin(θ/2))`` where θ is the angle between the reversed previous
    direction and the new one: straight on (θ = π) is unlimited, a reversal (θ = 0) is 0.
    """
    cos_theta = -sum(map(mul, prev_unit, unit))
    if cos_theta > 0.999999:
        return 0.0
    if cos_theta < -0.999999:
        return math.inf
    sin_half = math.sqrt(0.5 * (1.0 - cos_theta))
    return accel_mm_s2 * deviation_mm * sin_half / (1.0 - sin_half)


def axis_limits(unit: FloatArray, inverse_limits: FloatArray) -> FloatArray:
    """Per-axis limits projected on many directions at once.

    ``unit`` is (axes, blocks); ``inverse_limits`` holds 1/limit per kind of limit and axis,
    shaped (kinds, axes, 1) (say accelerations in mm/s² and max rates in mm/s). Returns the
    limits along each direction, (kinds, blocks): along ``u`` it is ``min_i limit_i/|u_i|``.
    A zero vector (a zero-length block) gets :data:`STILL_LIMIT`: finite, so ``2·a·d`` is 0 and
    a ramp without a change of speed takes no time, and small enough that its square is finite.
    """
    worst = np.maximum.reduce(np.abs(unit) * inverse_limits, axis=1)
    np.maximum(worst, 1.0 / STILL_LIMIT, out=worst)
    limits: FloatArray = np.divide(1.0, worst, out=worst)
    return limits


def junction_speeds_sq(
    prev_unit: FloatArray,
    unit: FloatArray,
    accel_mm_s2: FloatArray,
    deviation_mm: float,
) -> FloatArray:
    """:func:`junction_speed_sq` for many junctions at once; units are (axes, junctions)."""
    cos_theta: FloatArray = -(prev_unit * unit).sum(axis=0)
    sin_half = np.sqrt(np.maximum(0.5 * (1.0 - cos_theta), 0.0))
    limit: FloatArray = accel_mm_s2 * deviation_mm * sin_half / np.maximum(1.0 - sin_half, 1e-300)
    limit[cos_theta > 0.999999] = 0.0
    limit[cos_theta < -0.999999] = np.inf
    return limit


def plan_window(
    length_mm: FloatArray,
    accel_mm_s2: FloatArray,
    nominal_mm_s: FloatArray,
    junction_sq: FloatArray,
    lead_s: FloatArray,
    start_mm_s: float,
    out: FloatArray,
) -> int:
    """Plan ``n`` blocks from the fixed start speed to a stop; write ``out`` (shape (7, n)).

    ``out`` rows: entry, cruise, exit speed (mm/s), first ramp, cruise, last ramp and total
    duration (s, total including ``lead_s``).

    Returns how many leading blocks are *settled*: their speeds stay the same however many
    blocks are appended to the window later. Appending replaces the end's term in the backward
    minimum, ``C[n] − C[i]``, by larger ones, so node ``i`` cannot change while that term is
    at least the node's own cap ``L[i]`` (the minimum is then at most ``L[i]`` without it).
    Block ``k`` counts while every node up to its exit ``k + 1 < n`` passes that test (its
    entry is then settled too, the head's being fixed); the last block never counts.
    """
    n = length_mm.shape[0]
    cum = np.empty(n + 1)
    cum[0] = 0.0
    np.add.accumulate(2.0 * accel_mm_s2 * length_mm, out=cum[1:])
    caps = node_caps(nominal_mm_s, junction_sq[1:])
    caps[n - 1] = 0.0  # the end of the window: a stop
    end = float(cum[n])
    return plan_prefix(length_mm, accel_mm_s2, nominal_mm_s, lead_s, caps, cum, end, end, True,
                       start_mm_s, out)


def node_caps(nominal_mm_s: FloatArray, junction_sq: FloatArray) -> FloatArray:
    """Caps on v² of the nodes between consecutive blocks (mm²/s²): the junction limits
    (one per node) and both neighbours' nominal speeds; one more slot at the end, unset."""
    caps = np.empty(nominal_mm_s.shape[0])
    nominal_sq = nominal_mm_s * nominal_mm_s
    np.minimum(nominal_sq[:-1], nominal_sq[1:], out=caps[:-1])
    np.minimum(caps[:-1], junction_sq, out=caps[:-1])
    return caps


def plan_prefix(
    length_mm: FloatArray,
    accel_mm_s2: FloatArray,
    nominal_mm_s: FloatArray,
    lead_s: FloatArray,
    caps_sq: FloatArray,
    cum: FloatArray,
    end_term: float,
    end_cum: float,
    whole: bool,
    start_mm_s: float,
    out: FloatArray,
) -> int:
    """Plan the first ``n`` blocks of a window exactly as planning the whole window would.

    Only nodes ``0..n`` are computed: the rest of the window enters through ``end_term``, the
    minimum of ``L[j] + C[j]`` over its nodes ``j ≥ n`` (its end's term is ``C`` there, its
    cap being 0), which is all the backward pass needs of them. ``caps_sq`` holds ``L`` of
    nodes ``1..n`` (node ``n``'s is 0 when the prefix is the ``whole`` window); ``cum`` holds
    ``C`` at nodes ``0..n`` from any origin; ``end_cum`` is ``C`` at the end of the window.
    Writes ``out`` and returns the settled blocks as :func:`plan_window` does.
    """
    n = length_mm.shape[0]
    two_ad = 2.0 * accel_mm_s2 * length_mm
    caps = np.empty(n + 1)
    caps[0] = np.inf
    caps[1:] = caps_sq
    tested = n - 1 if whole else n  # the end of the window is no cap: it never settles
    settled = tested
    if tested > 0:
        unsettled = end_cum - cum[1 : tested + 1] < caps[1 : tested + 1]
        first = int(unsettled.argmax())
        settled = first if unsettled[first] else settled
    terms = caps + cum
    terms[n] = end_term
    backward = np.minimum.accumulate(terms[::-1])[::-1]
    backward -= cum
    np.minimum(backward, caps, out=backward)  # exact where a node's own cap binds
    start_sq = start_mm_s * start_mm_s
    if start_sq > backward[0] * OVER_SPEED:  # see the module docstring
        np.maximum(backward, (start_sq + cum[0]) - cum, out=backward)
    limit = backward
    limit[0] = start_sq
    speed_sq = np.minimum.accumulate(limit - cum)
    speed_sq += cum
    np.minimum(speed_sq, limit, out=speed_sq)
    np.maximum(speed_sq, 0.0, out=speed_sq)
    _trapezoids(length_mm, accel_mm_s2, nominal_mm_s, lead_s, two_ad, speed_sq, out)
    return int(settled)


def _trapezoids(
    length_mm: FloatArray,
    accel_mm_s2: FloatArray,
    nominal_mm_s: FloatArray,
    lead_s: FloatArray,
    two_ad: FloatArray,
    speed_sq: FloatArray,
    out: FloatArray,
) -> None:
    """Trapezoid (or triangle, when there is no room to cruise) of every block, vectorised."""
    entry, cruise, exit_, ramp1, flat, ramp2, total = out
    speed = np.sqrt(speed_sq)
    entry[:] = speed[:-1]
    exit_[:] = speed[1:]
    peak = np.sqrt(0.5 * (two_ad + speed_sq[:-1] + speed_sq[1:]))
    np.minimum(peak, np.maximum(nominal_mm_s, np.minimum(entry, exit_)), out=cruise)
    np.divide(np.abs(cruise - entry), accel_mm_s2, out=ramp1)
    np.divide(np.abs(cruise - exit_), accel_mm_s2, out=ramp2)
    ramp_mm = (entry + cruise) * ramp1
    ramp_mm += (cruise + exit_) * ramp2
    flat_mm = np.maximum(length_mm - 0.5 * ramp_mm, 0.0)
    np.divide(flat_mm, np.maximum(cruise, 1e-300), out=flat)  # zero-length blocks: 0 / tiny
    np.add(ramp1, flat, out=total)
    total += ramp2
    total += lead_s


def plan_window_reference(
    length_mm: Sequence[float],
    accel_mm_s2: Sequence[float],
    nominal_mm_s: Sequence[float],
    junction_sq: Sequence[float],
    lead_s: Sequence[float],
    start_mm_s: float,
) -> list[list[float]]:
    """The same plan as :func:`plan_window`, in plain Python loops; returns the 7 rows."""
    n = len(length_mm)
    two_ad = [2.0 * a * d for a, d in zip(accel_mm_s2, length_mm, strict=True)]
    caps = [math.inf] * (n + 1)
    for k in range(1, n):
        caps[k] = min(junction_sq[k], nominal_mm_s[k - 1] ** 2, nominal_mm_s[k] ** 2)
    caps[n] = 0.0
    backward = [0.0] * (n + 1)
    for i in range(n - 1, -1, -1):
        backward[i] = min(caps[i], backward[i + 1] + two_ad[i])
    speed_sq = [start_mm_s * start_mm_s] * (n + 1)
    falling = speed_sq[0]
    for i in range(n):
        falling -= two_ad[i]
        limit = max(backward[i + 1], falling)
        speed_sq[i + 1] = max(min(limit, speed_sq[i] + two_ad[i]), 0.0)
    rows: list[list[float]] = [[] for _ in range(PROFILE_ROWS)]
    for k in range(n):
        limits = (length_mm[k], accel_mm_s2[k], nominal_mm_s[k], lead_s[k])
        _trapezoid_reference(*limits, speed_sq[k], speed_sq[k + 1], rows)
    return rows


def _trapezoid_reference(
    length_mm: float,
    accel_mm_s2: float,
    nominal_mm_s: float,
    lead_s: float,
    entry_sq: float,
    exit_sq: float,
    rows: list[list[float]],
) -> None:
    entry, exit_ = math.sqrt(entry_sq), math.sqrt(exit_sq)
    peak = math.sqrt(0.5 * (2.0 * accel_mm_s2 * length_mm + entry_sq + exit_sq))
    cruise = min(peak, max(nominal_mm_s, min(entry, exit_)))
    ramp1 = abs(cruise - entry) / accel_mm_s2
    ramp2 = abs(cruise - exit_) / accel_mm_s2
    flat_mm = max(length_mm - 0.5 * ((entry + cruise) * ramp1 + (cruise + exit_) * ramp2), 0.0)
    flat = flat_mm / cruise if cruise > 0.0 else 0.0
    for row, value in zip(
        rows, (entry, cruise, exit_, ramp1, flat, ramp2, ramp1 + flat + ramp2 + lead_s), strict=True
    ):
        row.append(value)
