"""Arc geometry for G2/G3: the centre (R and IJK forms) and the chords that trace the arc.

Pure functions in machine millimetres. A plane is given by the indices of its two axes
``(a0, a1)`` in the order of G17 (X, Y), G18 (Z, X) and G19 (Y, Z); "clockwise" is seen looking
down the third axis, as in Grbl and LinuxCNC. Every other axis moves linearly (helix).

Hostile numbers end in error 33 (invalid target), never in an exception or an endless loop:
an R-form arc so flat that its sweep rounds to nothing (it would become a full circle), a
centre or radius that is not finite, and an arc needing more than :data:`MAX_CHORDS` chords
(about 30 ms of interpreter work; a full circle of 2 m radius at the finest ``$12``).
"""

from __future__ import annotations

import math

from server.errors import CommandError, Error
from server.motion.moves import Position

FULL_CIRCLE_EPSILON_RAD = 5e-7  # Grbl's ARC_ANGULAR_TRAVEL_EPSILON
MAX_SEGMENT_RAD = math.pi / 2
MAX_CHORDS = 10_000


def radius_form_centre(
    start: Position, end: Position, plane: tuple[int, int], r_mm: float, clockwise: bool
) -> tuple[float, float]:
    """The centre of an R-form arc (Grbl's construction); a negative R takes the long way.

    Raises:
        CommandError: 33 when the end equals the start in the plane or the arc is too flat to
            have a direction (its sweep rounds to zero), 34 when no circle of radius R passes
            through both points.
    """
    a0, a1 = plane
    dx, dy = end[a0] - start[a0], end[a1] - start[a1]
    chord = math.hypot(dx, dy)
    if chord == 0.0:
        raise CommandError(Error.INVALID_TARGET, "R-form arc: end point equals start point")
    if not math.isfinite(chord * r_mm):
        raise CommandError(Error.INVALID_TARGET, "R-form arc: radius or end point out of range")
    centre = _radius_centre(start, plane, dx, dy, chord, r_mm, clockwise)
    travel = _raw_travel(start, end, plane, centre)
    if abs(travel) <= FULL_CIRCLE_EPSILON_RAD:
        raise CommandError(
            Error.INVALID_TARGET,
            f"R-form arc: radius {abs(r_mm):g} mm is too large for a chord of {chord:g} mm "
            "(the arc is a straight line: use G1)",
        )
    return centre


def _radius_centre(
    start: Position,
    plane: tuple[int, int],
    dx: float,
    dy: float,
    chord: float,
    r_mm: float,
    clockwise: bool,
) -> tuple[float, float]:
    a0, a1 = plane
    h_squared_x4 = 4.0 * r_mm * r_mm - chord * chord
    if h_squared_x4 < 0.0:
        if h_squared_x4 < -1e-9 * chord * chord:
            raise CommandError(
                Error.ARC_RADIUS_ERROR,
                f"arc radius {abs(r_mm):g} mm is too small for a chord of {chord:g} mm",
            )
        h_squared_x4 = 0.0  # a half circle whose R was rounded when written
    h_x2_div_d = -math.sqrt(h_squared_x4) / chord
    if not clockwise:
        h_x2_div_d = -h_x2_div_d
    if r_mm < 0.0:
        h_x2_div_d = -h_x2_div_d
    return (start[a0] + 0.5 * (dx - dy * h_x2_div_d), start[a1] + 0.5 * (dy + dx * h_x2_div_d))


def _raw_travel(
    start: Position, end: Position, plane: tuple[int, int], centre: tuple[float, float]
) -> float:
    """The signed angle from start to end around ``centre``, in (-pi, pi]."""
    a0, a1 = plane
    r0, r1 = start[a0] - centre[0], start[a1] - centre[1]
    t0, t1 = end[a0] - centre[0], end[a1] - centre[1]
    return math.atan2(r0 * t1 - r1 * t0, r0 * t0 + r1 * t1)


def check_offset_radius(
    start: Position, end: Position, plane: tuple[int, int], centre: tuple[float, float]
) -> None:
    """Grbl's radius check for IJK arcs: start and end radii may differ by 0.005 mm, or by
    up to 0.5 mm when that is within 0.1 % of the radius.

    Raises:
        CommandError: 33 when the end point is not on the arc.
    """
    a0, a1 = plane
    r_start = math.hypot(start[a0] - centre[0], start[a1] - centre[1])
    r_end = math.hypot(end[a0] - centre[0], end[a1] - centre[1])
    delta = abs(r_end - r_start)
    if delta > 0.005 and (delta > 0.5 or delta > 0.001 * r_start):
        raise CommandError(
            Error.INVALID_TARGET,
            f"arc end point is {delta:.4f} mm off the circle "
            f"(radius {r_start:.4f} mm at the start, {r_end:.4f} mm at the end)",
        )
    if r_start == 0.0:
        raise CommandError(Error.INVALID_TARGET, "arc centre equals the start point")


def angular_travel(
    start: Position,
    end: Position,
    plane: tuple[int, int],
    centre: tuple[float, float],
    clockwise: bool,
) -> float:
    """Signed angle swept from start to end (negative clockwise); end == start is a full turn."""
    travel = _raw_travel(start, end, plane, centre)
    if clockwise:
        if travel >= -FULL_CIRCLE_EPSILON_RAD:
            travel -= 2.0 * math.pi
    elif travel <= FULL_CIRCLE_EPSILON_RAD:
        travel += 2.0 * math.pi
    return travel


def segment_count(travel_rad: float, radius_mm: float, tolerance_mm: float) -> int:
    """How many chords keep the sagitta ``r(1 - cos(θ/2))`` within ``tolerance_mm``.

    Raises:
        CommandError: 33 when the sweep or radius is not finite, or the arc would need more
            than MAX_CHORDS chords.
    """
    if not (math.isfinite(travel_rad) and math.isfinite(radius_mm) and tolerance_mm > 0):
        raise CommandError(Error.INVALID_TARGET, "arc centre or radius out of range")
    ratio = tolerance_mm / (2.0 * radius_mm) if radius_mm > 0 else 1.0
    max_angle = 4.0 * math.asin(math.sqrt(ratio)) if ratio < 1.0 else MAX_SEGMENT_RAD
    count = math.ceil(abs(travel_rad) / min(max_angle, MAX_SEGMENT_RAD) - 1e-9)
    if count > MAX_CHORDS:
        raise CommandError(
            Error.INVALID_TARGET,
            f"arc would need {count} chords (at most {MAX_CHORDS}): radius too large for $12",
        )
    return max(count, 1)


def chords(
    start: Position,
    end: Position,
    plane: tuple[int, int],
    centre: tuple[float, float],
    clockwise: bool,
    tolerance_mm: float,
) -> list[Position]:
    """The end points of the chords tracing the arc; the last one is exactly ``end``.

    The radius is interpolated linearly from the start radius to the end radius (a spiral when
    they differ within the allowed error) and every axis outside the plane moves linearly.
    """
    a0, a1 = plane
    c0, c1 = centre
    r_start = math.hypot(start[a0] - c0, start[a1] - c1)
    r_end = math.hypot(end[a0] - c0, end[a1] - c1)
    travel = angular_travel(start, end, plane, centre, clockwise)
    count = segment_count(travel, max(r_start, r_end), tolerance_mm)
    angle0 = math.atan2(start[a1] - c1, start[a0] - c0)
    points: list[Position] = []
    for k in range(1, count):
        fraction = k / count
        angle = angle0 + travel * fraction
        radius = r_start + (r_end - r_start) * fraction
        point = [s + (e - s) * fraction for s, e in zip(start, end, strict=True)]
        point[a0] = c0 + radius * math.cos(angle)
        point[a1] = c1 + radius * math.sin(angle)
        points.append(tuple(point))
    points.append(tuple(end))
    return points
