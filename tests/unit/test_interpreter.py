"""The G-code interpreter: conformance table, outputs, arcs, jogs, reports and the fast path."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.errors import CommandError, SoftLimitError
from server.gcode.interpreter import Interpreter, InterpreterSettings
from server.gcode.parser import Line, parse_line
from server.motion.moves import Action, Move, MoveKind, Output, Sync, ToolMode

XYZ = InterpreterSettings(("X", "Y", "Z"), (-1000.0,) * 3, (1000.0,) * 3)
SMALL = InterpreterSettings(("X", "Y", "Z"), (0.0, 0.0, -50.0), (300.0, 200.0, 0.0))


def run(lines: list[str], machine: InterpreterSettings = XYZ) -> tuple[Interpreter, list[Output]]:
    interpreter = Interpreter(machine)
    outputs: list[Output] = []
    for text in lines:
        outputs = interpreter.execute(parse_line(text))
    return interpreter, outputs


def moves(outputs: list[Output]) -> list[Move]:
    return [output for output in outputs if isinstance(output, Move)]


def state_of(interpreter: Interpreter) -> tuple[Any, ...]:
    return (interpreter.position, interpreter.wco(), interpreter.gc_report(),
            interpreter.offsets_report(), interpreter.modal_snapshot())


def close(a: tuple[float, ...], b: tuple[float, ...], tolerance: float = 1e-9) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= tolerance for x, y in zip(a, b, strict=True))


# -- the conformance table -------------------------------------------------------------------
@dataclass
class Case:
    lines: list[str]
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    gc: tuple[str, ...] = ()
    error: int | None = None


TABLE: dict[str, Case] = {
    # motion, units, distance modes
    "g0 goes to absolute work coordinates": Case(["G0 X10 Y20 Z-5"], (10, 20, -5), (10, 20, -5)),
    "g1 sets motion mode and feed": Case(["G1 X10 F100"], (10, 0, 0), gc=("G1", "F100")),
    "g20 scales axis words to mm": Case(["G20 G0 X1"], (25.4, 0, 0), (25.4, 0, 0), ("G20",)),
    "g91 with g20 moves by inches": Case(["G0 X10", "G20 G91 G0 X1 Y-1"], (35.4, -25.4, 0),
                                         gc=("G20", "G91")),
    "g90 after g91 is absolute again": Case(["G91 G0 X5", "G0 X5", "G90 G0 X1"], (1, 0, 0)),
    "axis words alone use the modal motion": Case(["G1 F100", "X5", "Y5"], (5, 5, 0)),
    "f on a g0 line sets the modal feed": Case(["G0 X1 F300"], gc=("G0", "F300")),
    "f shows in mm/min under g20, as grbl": Case(["G1 F254", "G20"], gc=("F254 ",)),
    "block delete lines are skipped": Case(["/G0 X10"], (0, 0, 0)),
    "comment lines do nothing": Case(["(just a comment)", "; another"], (0, 0, 0)),
    # coordinate systems
    "g55 uses its own offset": Case(["G10 L2 P2 X10 Y20", "G55 G0 X0 Y0"], (10, 20, 0), (0, 0, 0),
                                    ("G55",)),
    "g59.1 is the seventh system": Case(["G10 L2 P7 X5", "G59.1 G0 X0"], (5, 0, 0),
                                        gc=("G59.1",)),
    "g10 l2 p0 sets the current system": Case(["G55", "G10 L2 P0 X7", "G0 X0"], (7, 0, 0)),
    "g10 l2 ignores g91": Case(["G91 G10 L2 P1 X3", "G90 G0 X0"], (3, 0, 0)),
    "g10 l20 makes the position read as given": Case(["G0 X10 Y10", "G10 L20 P1 X0 Y5"],
                                                     (10, 10, 0), (0, 5, 0)),
    "g10 l20 in inches": Case(["G0 X10", "G20 G10 L20 P1 X1"], (10, 0, 0), (25.4, 0, 0)),
    "g92 makes the position read as given": Case(["G0 X10", "G92 X0"], (10, 0, 0), (0, 0, 0)),
    "g92 with g54 offset active": Case(["G10 L2 P1 X5", "G0 X10", "G92 X2", "G0 X0"],  # 15 reads 2
                                       (13, 0, 0), (0, 0, 0)),
    "g92 applies on top of any system": Case(["G92 X-5", "G10 L2 P2 X10", "G55 G0 X0"],
                                             (15, 0, 0), (0, 0, 0)),
    "g92.1 clears g92": Case(["G0 X10", "G92 X0", "G92.1"], (10, 0, 0), (10, 0, 0)),
    "g92.2 suspends g92": Case(["G0 X10", "G92 X0", "G92.2"], (10, 0, 0), (10, 0, 0)),
    "g92.3 restores g92": Case(["G0 X10", "G92 X0", "G92.2", "G92.3"], (10, 0, 0), (0, 0, 0)),
    "g53 within g91 is absolute machine": Case(["G91", "G53 G0 X50 Y-20"], (50, -20, 0),
                                               gc=("G91",)),
    "g53 ignores the work offset": Case(["G10 L2 P1 X100", "G53 G1 X5 F100"], (5, 0, 0),
                                        (-95, 0, 0)),
    "g53 in inches": Case(["G20", "G53 G0 X1"], (25.4, 0, 0)),
    "g43.1 offsets z": Case(["G43.1 Z5", "G0 Z0"], (0, 0, 5), (0, 0, 0)),
    "g49 cancels the tool offset": Case(["G43.1 Z5", "G49", "G0 Z0"], (0, 0, 0)),
    # predefined positions
    "g28 goes through the intermediate point": Case(
        ["G0 X50 Y50", "G28.1", "G0 X10 Y20 Z5", "G28 Z10"], (10, 20, 0)),
    "g28 without axes goes straight home": Case(
        ["G0 X50 Y50 Z5", "G28.1", "G0 X0 Y0 Z0", "G28"], (50, 50, 5)),
    "g91 g30 z0 lifts z to the stored height": Case(
        ["G0 X50 Y50 Z5", "G30.1", "G0 X1 Y2 Z3", "G91 G30 Z0"], (1, 2, 5)),
    # arcs
    "g2 ij quarter circle": Case(["G0 X0 Y10", "G2 X10 Y0 I0 J-10 F100"], (10, 0, 0)),
    "g2 negative r takes the long way": Case(["G2 X10 Y0 R-10 F100"], (10, 0, 0)),
    "full circle with ij only": Case(["G0 X10", "G2 I-10 J0 F100"], (10, 0, 0), gc=("G2",)),
    "helix ends at its height": Case(["G0 X10", "G3 X-10 Y0 Z5 I-10 F100"], (-10, 0, 5)),
    "g18 arc": Case(["G0 X10", "G18 G2 X0 Z10 I-10 K0 F100"], (0, 0, 10), gc=("G18",)),
    "g19 arc": Case(["G0 Y10", "G19 G3 Y0 Z10 J-10 F100"], (0, 0, 10), gc=("G19",)),
    "g90.1 absolute centre": Case(["G90.1", "G0 X10", "G2 X-10 I0 J0 F100"], (-10, 0, 0)),
    "r arc in inches": Case(["G20", "G0 X1", "G2 X-1 Y0 R1 F10"], (-25.4, 0, 0)),
    "g91 helix": Case(["G0 X10", "G91 G2 X-20 Z-2 I-10 F100"], (-10, 0, -2)),
    # modes without motion
    "g80 cancels motion": Case(["G1 F100", "G80"], gc=("G80",)),
    "spindle and coolant modes": Case(["M3 S1000", "M8"], gc=("M3", "M8", "S1000")),
    "mist and flood together": Case(["M7", "M8"], gc=("M7 M8",)),
    "m9 turns both off": Case(["M7", "M8", "M9"], gc=("M9",)),
    "t selects a tool": Case(["T5"], gc=("T5",)),
    "t with m6": Case(["T3 M6"], gc=("T3",)),
    "path and cutter modes are accepted": Case(["G61", "G61.1", "G64", "G40"], (0, 0, 0)),
    "g93 shows in gc": Case(["G93"], gc=("G93",)),
    "program end resets modes": Case(["G10 L2 P2 X10", "G55 G91 G18 G0 X1", "M3 S100 M7", "M2"],
                                     gc=("G1 G54 G17 G21 G90 G94 M5 M9",)),
    "m30 ends too": Case(["G91", "M30"], gc=("G1 G54 G17 G21 G90 G94",)),
    "g38.2 probes": Case(["G38.2 Z-10 F100"], (0, 0, -10), gc=("G38.2",)),
    # errors
    "g0 g1: two axis commands, as Grbl checks first": Case(["G0 G1 X1"], error=24),
    "g80 g0 is a modal group violation": Case(["G80 G0 X1"], error=21),
    "g90 g91 is a modal group violation": Case(["G90 G91"], error=21),
    "m3 m4 is a modal group violation": Case(["M3 M4"], error=21),
    "m7 m8 on one line is a modal group violation": Case(["M7 M8"], error=21),
    "g1 with g92 is an axis command conflict": Case(["G1 G92 X0"], error=24),
    "repeated x": Case(["G0 X1 X2"], error=25),
    "axis words under g80": Case(["G1 F100", "G80", "X10"], error=31),
    "g80 with axis words": Case(["G80 X10"], error=31),
    "g49 with axis words": Case(["G49 X1"], error=31),
    "i with g0": Case(["G0 X1 I5"], error=36),
    "r with g1": Case(["G1 X1 R5 F100"], error=36),
    "p without g4": Case(["G0 X1 P5"], error=36),
    "r and ij together": Case(["G2 X10 R5 I5 F100"], error=36),
    "g1 without any feed": Case(["G1 X10"], error=22),
    "explicit g1 without any feed": Case(["G1"], error=22),
    "g93 move without f": Case(["G93 G1 X10 F100", "G1 X20"], error=22),
    "switching to g93 needs f": Case(["G1 F100", "G93 G1 X10"], error=22),
    "g93 to g94 leaves feed undefined": Case(["G93 G1 X1 F60", "G94 G1 X2"], error=22),
    "probe without feed": Case(["G38.2 Z-10"], error=22),
    "m3.5 needs an integer": Case(["M3.5"], error=23),
    "t1.5 needs an integer": Case(["T1.5"], error=23),
    "g10 l2.5 needs an integer": Case(["G10 L2.5 P1 X0"], error=23),
    "g10 p1.5 needs an integer": Case(["G10 L2 P1.5 X0"], error=23),
    "g1.5: g1 takes no decimals": Case(["G1.5 X1"], error=23),
    "g38.1 does not exist": Case(["G38.1 Z1 F10"], error=20),
    "g90.5: g90 takes no decimals": Case(["G90.5"], error=23),
    "g38.6 does not exist": Case(["G38.6 X1 F10"], error=20),
    "negative f": Case(["F-1"], error=4),
    "negative s": Case(["S-1"], error=4),
    "negative p": Case(["G4 P-1"], error=4),
    "negative t": Case(["T-1"], error=4),
    "g92 without axes": Case(["G92"], error=26),
    "g10 without axes": Case(["G10 L2 P1"], error=26),
    "g2 without axes or offsets": Case(["G2 F100"], error=26),
    "g2 r without axes": Case(["G2 R5 F100"], error=26),
    "probe without axes": Case(["G38.2 F100"], error=26),
    "g4 without p": Case(["G4"], error=28),
    "g10 without l": Case(["G10 P1 X0"], error=28),
    "g10 without p is the active system": Case(["G55", "G10 L2 X5", "G0 X0"], (5, 0, 0)),
    "g10 p10": Case(["G10 L2 P10 X0"], error=29),
    "g10 l20 p12": Case(["G10 L20 P12 X0"], error=29),
    "g10 l1 tool table": Case(["G10 L1 P1 X0"], error=20),
    "g53 with g2": Case(["G53 G2 X10 I5 F100"], error=30),
    "g53 with modal g2": Case(["G1 F100", "G2 X10 I5", "G53 X0"], error=30),
    "g43.1 with x": Case(["G43.1 X1"], error=37),
    "g43.1 with z and x": Case(["G43.1 Z1 X1"], error=37),
    "g43.1 alone": Case(["G43.1"], error=37),
    "t256": Case(["T256"], error=38),
    "arc r without in-plane axis": Case(["G2 Z5 R5 F100"], error=32),
    "arc without in-plane axis or offset": Case(["G2 Z5 F100"], error=32),
    "arc without in-plane offset": Case(["G2 X10 F100"], error=35),
    "arc with only an out-of-plane offset": Case(["G2 X10 K5 F100"], error=35),
    "arc end off the circle": Case(["G2 X10 I4 F100"], error=33),
    "arc 0.004 mm off is accepted": Case(["G2 X10.004 I5 F100"], (10.004, 0, 0)),
    "arc 0.006 mm off a 5 mm radius": Case(["G2 X10.006 I5 F100"], error=33),
    "arc 0.09 mm off a 100 mm radius is accepted": Case(["G2 X200.09 I100 F100"],
                                                        (200.09, 0, 0)),
    "arc 0.11 mm off a 100 mm radius": Case(["G2 X200.11 I100 F100"], error=33),
    "arc 0.45 mm off a 600 mm radius is accepted": Case(["G0 X-600", "G2 X600.45 I600 F1"],
                                                        (600.45, 0, 0)),
    "arc 0.55 mm off a 600 mm radius": Case(["G0 X-600", "G2 X600.55 I600 F1"], error=33),
    "r arc to its own start": Case(["G2 X0 Y0 R5 F100"], error=33),
    "r too small for the chord": Case(["G2 X20 R5 F100"], error=34),
    "r so large the arc is a line": Case(["G2 X10 R100000000 F100"], error=33),
    "r so large the long way is a circle": Case(["G2 X0.0001 R-1000 F100"], error=33),
    "r large but the arc has a sweep": Case(["G2 X10 R10000 F100"], (10, 0, 0)),
    "arc needing over 10000 chords": Case(["G2 I100000 F100"], error=33),
    "dwell of an hour": Case(["G4 P3600"], (0, 0, 0)),
    "dwell over an hour": Case(["G4 P3600.5"], error=2),
    "g41 cutter compensation": Case(["G41 D1"], error=20),
    "g42 cutter compensation": Case(["G42"], error=20),
    "canned cycle is never a plain move": Case(["G81 X50 Y60 Z-5 R1 F100"], error=20),
    "g73 canned cycle": Case(["G73 X1 Y1 Z-1 R1 Q1 F100"], error=20),
    "g43 tool table offset": Case(["G43 H1"], error=20),
    "o words": Case(["O100"], error=20),
    "printer temperature": Case(["M104 S200"], error=20),
    "extruder word": Case(["G1 X1 E5 F100"], error=20),
    "unconfigured axis": Case(["G0 A10"], error=20),
    "unknown m code": Case(["M62 P1"], error=20),
    "soft limit": Case(["G0 X1001"], error=40),
    "soft limit on an arc bulge": Case(["G0 X999", "G3 X999 Y10 R5 F100"], error=40),
    "soft limit on g28 intermediate point": Case(["G28 X2000"], error=40),
    "error after state changes": Case(["G20 G91 G55 M3 S100 T2 G43.1 Z1 G92.1", "G0 G1 X1"],
                                      error=24),
}


@pytest.mark.parametrize("case", TABLE.values(), ids=TABLE.keys())
def test_conformance_table(case: Case) -> None:
    interpreter = Interpreter(XYZ)
    for text in case.lines[:-1]:
        interpreter.execute(parse_line(text))
    last = parse_line(case.lines[-1])
    if case.error is not None:
        before = state_of(interpreter)
        with pytest.raises(CommandError) as caught:
            interpreter.execute(last)
        assert caught.value.code == case.error
        assert state_of(interpreter) == before
        return
    interpreter.execute(last)
    if case.mpos is not None:
        assert close(interpreter.position, tuple(map(float, case.mpos)))
    if case.wpos is not None:
        work = interpreter.work_position(interpreter.position)
        assert close(work, tuple(map(float, case.wpos)))
    for snippet in case.gc:
        assert snippet in interpreter.gc_report()


def test_power_on_gc_report_matches_grbl() -> None:
    assert Interpreter(XYZ).gc_report() == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"


BUSY_HISTORY = ["G10 L2 P2 X3 Y4", "G55 G20 G91", "G92 X1", "G43.1 Z0.5", "M3 S900 M8 T4",
                "G1 X1 F20", "G2 X1 Y1 I1", "G90.1 G93 G18"]
BAD_AFTER_BUSY = ["G0 G1 X1", "G1 X1 R5 F1", "G1 X1", "M3.5 S1", "G10 L2 P10 X0", "G43.1 X1",
                  "T256", "G81 X1", "G1 X1 E1 F1", "G2 X1 F100", "G0 X2000", "G53 G2 X1 I1 F1",
                  "G4", "G92", "G28 X2000", "G38.2 F10", "G3 X0 Z0 R1 F1", "S-5 G0 X0"]


@pytest.mark.parametrize("bad", BAD_AFTER_BUSY)
def test_a_refused_line_leaves_a_busy_state_exactly_unchanged(bad: str) -> None:
    interpreter, _ = run(BUSY_HISTORY)
    before = state_of(interpreter)
    with pytest.raises(CommandError):
        interpreter.execute(parse_line(bad))
    assert state_of(interpreter) == before


# -- outputs and their order -----------------------------------------------------------------
def test_g1_feed_is_converted_from_mm_per_min_to_mm_per_s() -> None:
    _, out = run(["G1 X10 F600"])
    assert moves(out)[0].feed_mm_s == pytest.approx(10.0)
    assert moves(out)[0].kind is MoveKind.FEED


def test_g20_feed_is_converted_from_inches_per_min() -> None:
    _, out = run(["G20 G1 X1 F10"])
    assert moves(out)[0].feed_mm_s == pytest.approx(10 * 25.4 / 60)
    assert moves(out)[0].target_mm == pytest.approx((25.4, 0, 0))


def test_rapids_have_infinite_feed_for_the_planner_to_cap() -> None:
    for line in ("G0 X5", "G53 G0 X5", "G28"):
        _, out = run(["G0 X1", line])
        assert all(m.kind is MoveKind.RAPID and m.feed_mm_s == math.inf for m in moves(out))


def test_g93_inverse_time_makes_each_move_last_60_over_f_seconds() -> None:
    _, out = run(["G93 G1 X30 F2"])
    move = moves(out)[0]
    assert 30.0 / move.feed_mm_s == pytest.approx(30.0)


def test_g93_arc_chords_share_one_speed_that_takes_60_over_f_seconds() -> None:
    _, out = run(["G0 X10", "G93 G2 X-10 I-10 F6"])
    chords = moves(out)
    previous: tuple[float, ...] = (10.0, 0.0, 0.0)
    length = 0.0
    for chord in chords:
        length += math.dist(previous, chord.target_mm)
        previous = chord.target_mm
    assert {chord.feed_mm_s for chord in chords} == {chords[0].feed_mm_s}
    assert length / chords[0].feed_mm_s == pytest.approx(10.0)


def test_spindle_action_rides_at_the_start_of_the_move_on_the_same_line() -> None:
    _, out = run(["M3 S1000 M8 G1 X10 F100"])
    assert len(out) == 1 and isinstance(out[0], Move)
    assert out[0].actions == [Action("spindle", {"mode": ToolMode.CW, "s": 1000.0}),
                              Action("coolant", {"mist": False, "flood": True})]
    assert out[0].tool_mode is ToolMode.CW and out[0].s_value == 1000.0


def test_an_s_change_emits_a_spindle_action_in_the_move_or_alone() -> None:
    interpreter, _ = run(["M4 S0", "G1 X1 F100"])
    out = interpreter.execute(parse_line("X2 S40"))  # the fast path
    assert len(out) == 1 and isinstance(out[0], Move) and out[0].s_value == 40.0
    assert out[0].actions == [Action("spindle", {"mode": ToolMode.CCW, "s": 40.0})]
    again = interpreter.execute(parse_line("X3 S40"))[0]
    assert isinstance(again, Move) and again.s_value == 40.0 and again.actions == []
    assert interpreter.execute(parse_line("S50")) == [
        Action("spindle", {"mode": ToolMode.CCW, "s": 50.0})]


def test_follow_actions_before_a_sync_stay_in_order_with_it() -> None:
    _, out = run(["M8 M114"])
    assert [type(o).__name__ for o in out] == ["Action", "Sync"]


def test_coolant_dwell_pause_and_program_end_actions() -> None:
    _, out = run(["M7"])
    assert out == [Action("coolant", {"mist": True, "flood": False})]
    _, out = run(["G4 P0.5"])
    assert out == [Action("dwell", {"seconds": 0.5}, lead_s=0.5, stops_motion=True)]
    _, out = run(["M0"])
    assert out == [Action("pause", {"optional": False}, stops_motion=True)]
    _, out = run(["M1"])
    assert out == [Action("pause", {"optional": True}, stops_motion=True)]


def test_program_end_comes_after_the_move_and_turns_tools_off_first() -> None:
    _, out = run(["M3 S100 M8", "G1 X10 F100 M30"])
    assert isinstance(out[0], Move)
    assert [a.name for a in out[1:] if isinstance(a, Action)] == [
        "spindle", "coolant", "program_end"]
    assert out[1] == Action("spindle", {"mode": ToolMode.OFF, "s": 100.0})
    assert out[-1] == Action("program_end", {"code": 30}, stops_motion=True)


def test_dwell_runs_before_motion_on_the_same_line() -> None:
    _, out = run(["G1 F100", "G4 P1 X5"])
    assert isinstance(out[0], Action) and out[0].name == "dwell"
    assert isinstance(out[1], Move)


def test_t_alone_sets_the_tool_and_m6_changes_it() -> None:
    _, out = run(["T7"])
    assert out == []
    interpreter, out = run(["T7", "M6"])
    assert out == [Action("tool_change", {"tool": 7}, stops_motion=True)]
    assert "T7" in interpreter.gc_report()


def test_motor_commands() -> None:
    assert run(["M17"])[1] == [Action("motors", {"enabled": True})]
    for code in ("M18", "M84"):
        assert run([code])[1] == [Action("motors", {"enabled": False}, stops_motion=True)]


def test_m114_m112_m999_become_sync_requests() -> None:
    assert run(["M114"])[1] == [Sync("report_position")]
    assert run(["M112"])[1] == [Sync("halt")]
    assert run(["M999"])[1] == [Sync("clear_halt")]


def test_m400_waits_after_the_lines_moves_and_m410_stops_before_them() -> None:
    assert run(["G1 X10 F600 M400"])[1][-1] == Sync("wait")
    assert run(["M410"])[1] == [Sync("quickstop")]


@pytest.mark.parametrize(("line", "kind"), [
    ("M21", "query"), ("M400", "query"), ("M114", "query"),
    ("M410", "unlock"), ("M112", "unlock"), ("M21 M3 S10", "effect"), ("M3", "effect")])
def test_unknown_codes_and_waits_are_answered_as_queries(line: str, kind: str) -> None:
    assert Interpreter(XYZ).classify(parse_line(line)).value == kind


def test_tools_off_leaves_a_reset_boards_m5_s0_m9_but_keeps_the_rest() -> None:
    interpreter, _ = run(["G91", "M3 S300", "M8"])
    interpreter.tools_off()
    assert interpreter.gc_report() == "[GC:G0 G54 G17 G21 G91 G94 M5 M9 T0 F0 S0]"


@pytest.mark.parametrize(("code", "towards", "error_on_fail"), [
    ("G38.2", True, True), ("G38.3", True, False), ("G38.4", False, True),
    ("G38.5", False, False)])
def test_probe_is_a_probe_move_followed_by_a_probe_sync(code: str, towards: bool,
                                                        error_on_fail: bool) -> None:
    _, out = run([f"{code} Z-10 F60"])
    assert isinstance(out[0], Move) and out[0].kind is MoveKind.PROBE
    assert out[0].target_mm == (0.0, 0.0, -10.0) and out[0].feed_mm_s == 1.0
    assert out[1] == Sync("probe", {"towards": towards, "error_on_fail": error_on_fail})


def test_probe_target_equal_to_position_is_error_33() -> None:
    with pytest.raises(CommandError) as caught:
        run(["G38.2 Z0 F60"])
    assert caught.value.code == 33


def test_g28_2_asks_the_dispatcher_to_home() -> None:
    assert run(["G28.2"])[1] == [Sync("home", {"axes": []})]
    assert run(["G28.2 X0 Z0"])[1] == [Sync("home", {"axes": [0, 2]})]


def test_g28_moves_through_the_intermediate_point() -> None:
    _, out = run(["G0 X50 Y50", "G28.1", "G0 X10 Y20 Z5", "G28 Z10"])
    assert [m.target_mm for m in moves(out)] == [(10.0, 20.0, 10.0), (10.0, 20.0, 0.0)]


def test_line_numbers_ride_in_the_moves() -> None:
    _, out = run(["N42 G1 X1 F100"])
    assert moves(out)[0].line_number == 42
    _, out = run(["N7 G2 X10 I5 F100"])
    assert {m.line_number for m in moves(out)} == {7}


def test_zero_length_moves_are_dropped() -> None:
    assert run(["G1 X5 F100", "X5"])[1] == []


def test_parser_errors_are_raised_as_they_are() -> None:
    line = parse_line("G1 X1*99")
    with pytest.raises(CommandError) as caught:
        Interpreter(XYZ).execute(line)
    assert caught.value is line.error


# -- soft limits -----------------------------------------------------------------------------
def test_soft_limit_raises_before_any_output_and_changes_nothing() -> None:
    interpreter, _ = run(["G0 X10 Y10", "M3 S10"], SMALL)
    before = state_of(interpreter)
    with pytest.raises(SoftLimitError):
        interpreter.execute(parse_line("M5 G0 X301"))
    assert state_of(interpreter) == before


def test_soft_limits_allow_a_billionth_of_slack() -> None:
    interpreter, _ = run(["G0 X300.0000000005 Z0.0000000005"], SMALL)
    assert interpreter.position[0] == 300.0000000005


def test_soft_limits_check_the_probe_target() -> None:
    with pytest.raises(SoftLimitError):
        run(["G38.2 Z-60 F100"], SMALL)


def test_soft_limits_can_be_turned_off_live() -> None:
    interpreter = Interpreter(SMALL)
    interpreter.settings = replace(SMALL, soft_limits=False)
    interpreter.execute(parse_line("G0 X-5"))
    assert interpreter.position == (-5.0, 0.0, 0.0)


# -- arcs ------------------------------------------------------------------------------------
def test_positive_r_takes_the_short_way_and_negative_r_the_long_way() -> None:
    _, short = run(["G2 X10 Y0 R10 F100"])
    _, long = run(["G2 X10 Y0 R-10 F100"])
    assert max(m.target_mm[1] for m in moves(short)) == pytest.approx(10 - 8.660254, abs=0.003)
    assert max(m.target_mm[1] for m in moves(long)) == pytest.approx(10 + 8.660254, abs=0.003)


def test_full_circle_with_ij_only_goes_all_the_way_round() -> None:
    _, out = run(["G0 X10", "G2 I-10 J0 F100"])
    points = [m.target_mm for m in moves(out)]
    assert min(p[0] for p in points) == pytest.approx(-10, abs=0.003)
    assert min(p[1] for p in points) == pytest.approx(-10, abs=0.003)
    assert points[-1] == (10.0, 0.0, 0.0)
    assert points[0][1] < 0  # G2 is clockwise: from +X it goes down first


def test_helix_climbs_linearly_and_ends_exactly_at_its_height() -> None:
    _, out = run(["G0 X10", "G3 X-10 Y0 Z5 I-10 F100"])
    heights = [m.target_mm[2] for m in moves(out)]
    steps = [b - a for a, b in zip([0.0, *heights], heights, strict=False)]
    assert heights[-1] == 5.0
    assert max(steps) - min(steps) < 1e-9


def test_g18_arc_stays_in_the_xz_plane() -> None:
    _, out = run(["G0 X10", "G18 G2 X0 Z10 I-10 F100"])
    points = [m.target_mm for m in moves(out)]
    assert all(p[1] == 0.0 and p[0] >= -1e-9 and p[2] >= -1e-9 for p in points)
    assert all(math.hypot(p[0], p[2]) == pytest.approx(10.0) for p in points)


def test_arc_chords_respect_a_coarser_tolerance() -> None:
    interpreter = Interpreter(replace(XYZ, arc_tolerance_mm=0.1))
    interpreter.execute(parse_line("G0 X10"))
    coarse = interpreter.execute(parse_line("G2 I-10 F100"))
    fine = run(["G0 X10", "G2 I-10 F100"])[1]
    assert len(coarse) < len(fine) / 5


def sagitta_of(chord_start: tuple[float, ...], chord_end: tuple[float, ...],
               centre: tuple[float, float], radius: float, step: float,
               start_angle: float) -> float:
    """Distance from the arc point midway between two chord ends to the chord."""
    middle = start_angle + step / 2
    arc_point = (centre[0] + radius * math.cos(middle), centre[1] + radius * math.sin(middle))
    (x1, y1), (x2, y2), (px, py) = chord_start, chord_end, arc_point
    length = math.hypot(x2 - x1, y2 - y1)
    if length == 0:
        return math.hypot(px - x1, py - y1)
    return abs((x2 - x1) * (y1 - py) - (x1 - px) * (y2 - y1)) / length


@settings(max_examples=150, deadline=None)
@given(radius=st.floats(0.05, 400), start=st.floats(-math.pi, math.pi),
       sweep=st.floats(0.01, 2 * math.pi - 0.01), clockwise=st.booleans(),
       tolerance=st.floats(0.0005, 0.2), climb=st.floats(-5, 5))
def test_chords_never_stray_from_the_arc_beyond_the_tolerance_and_end_exactly(
        radius: float, start: float, sweep: float, clockwise: bool, tolerance: float,
        climb: float) -> None:
    centre = (1.5, -2.5)
    begin = (centre[0] + radius * math.cos(start), centre[1] + radius * math.sin(start))
    end_angle = start - sweep if clockwise else start + sweep
    end = (centre[0] + radius * math.cos(end_angle), centre[1] + radius * math.sin(end_angle))
    interpreter = Interpreter(replace(XYZ, arc_tolerance_mm=tolerance))
    interpreter.set_position((begin[0], begin[1], 0.0))
    words = [("G", 2.0 if clockwise else 3.0), ("X", end[0]), ("Y", end[1]), ("Z", climb),
             ("I", centre[0] - begin[0]), ("J", centre[1] - begin[1]), ("F", 100.0)]
    out = interpreter.execute(Line.of("arc", words))
    points = [m.target_mm for m in moves(out)]
    assert points[-1] == (end[0], end[1], climb)
    direction = -1.0 if clockwise else 1.0
    angle, swept = start, 0.0
    previous: tuple[float, ...] = begin
    for point in points:
        step = (math.atan2(point[1] - centre[1], point[0] - centre[0]) - angle) * direction
        step = direction * (step % (2 * math.pi))
        assert sagitta_of(previous, point[:2], centre, radius, step, angle) <= tolerance + 1e-9
        angle, previous, swept = angle + step, point[:2], swept + abs(step)
    assert swept == pytest.approx(sweep, abs=1e-6)


# -- jogging ---------------------------------------------------------------------------------
def jog(interpreter: Interpreter, body: str) -> list[Move]:
    return interpreter.jog(parse_line(body))


def test_jog_moves_in_work_coordinates_and_leaves_the_modal_state_alone() -> None:
    interpreter, _ = run(["G10 L2 P1 X5", "G1 F100"])
    before = interpreter.gc_report()
    out = jog(interpreter, "G91 G20 X1 F10")
    assert out == [Move((25.4, 0.0, 0.0), 10 * 25.4 / 60, MoveKind.JOG)]
    assert interpreter.position == (25.4, 0.0, 0.0)
    assert interpreter.gc_report() == before
    assert jog(interpreter, "X0 F60")[0].target_mm == (5.0, 0.0, 0.0)


def test_jog_uses_the_modal_units_and_distance_when_the_line_does_not_say() -> None:
    interpreter, _ = run(["G20 G91"])
    assert jog(interpreter, "Y1 F1")[0].target_mm == pytest.approx((0, 25.4, 0))
    assert jog(interpreter, "G21 G90 Y1 F1")[0].target_mm == (0.0, 1.0, 0.0)


def test_jog_with_g53_is_in_machine_coordinates() -> None:
    interpreter, _ = run(["G10 L2 P1 X100", "G91"])
    assert jog(interpreter, "G53 X3 F100")[0].target_mm == (3.0, 0.0, 0.0)


@pytest.mark.parametrize("body", ["F100", "G1 X1 F100", "M3 X1 F100", "X1 S5 F100",
                                  "G2 X1 I1 F100", "E1 F100"])
def test_invalid_jogs_are_error_16(body: str) -> None:
    with pytest.raises(CommandError) as caught:
        jog(Interpreter(XYZ), body)
    assert caught.value.code == 16


@pytest.mark.parametrize("body", ["X1", "X1 F0"])
def test_a_jog_without_a_feed_is_error_22_as_in_grbl(body: str) -> None:
    with pytest.raises(CommandError) as caught:
        jog(Interpreter(XYZ), body)
    assert caught.value.code == 22


def test_jog_beyond_the_travel_is_error_15_and_changes_nothing() -> None:
    interpreter = Interpreter(SMALL)
    with pytest.raises(CommandError) as caught:
        jog(interpreter, "X-1 F100")
    assert caught.value.code == 15
    assert interpreter.position == (0.0, 0.0, 0.0)


# -- position, offsets, reports, reset -------------------------------------------------------
def test_set_position_resyncs_and_work_position_subtracts_the_offset() -> None:
    interpreter, _ = run(["G10 L2 P1 X1 Y2 Z3", "G43.1 Z0.5", "G92 X0"])
    interpreter.set_position((10, 20, 30))
    assert interpreter.position == (10.0, 20.0, 30.0)
    assert interpreter.wco() == (0.0, 2.0, 3.5)  # G92 X0 at machine 0 cancelled G54's X1
    assert interpreter.work_position((10.0, 20.0, 30.0)) == (10.0, 18.0, 26.5)


def test_offsets_report_lists_grbl_lines_in_order() -> None:
    interpreter, _ = run(["G10 L2 P2 X1.5", "G0 X5", "G28.1", "G92 X4", "G43.1 Z-1"])
    interpreter.record_probe((1.0, 2.0, -3.25), True)
    assert interpreter.offsets_report() == [
        "[G54:0.000,0.000,0.000]", "[G55:1.500,0.000,0.000]", "[G56:0.000,0.000,0.000]",
        "[G57:0.000,0.000,0.000]", "[G58:0.000,0.000,0.000]", "[G59:0.000,0.000,0.000]",
        "[G28:5.000,0.000,0.000]", "[G30:0.000,0.000,0.000]", "[G92:1.000,0.000,0.000]",
        "[TLO:-1.000]", "[PRB:1.000,2.000,-3.250:1]"]


def test_offsets_report_in_inches_with_report_inches() -> None:
    interpreter, _ = run(["G10 L2 P1 X25.4"], replace(XYZ, report_inches=True))
    assert interpreter.offsets_report()[0] == "[G54:1.0000,0.0000,0.0000]"


def test_gc_report_after_a_program_prologue() -> None:
    interpreter, _ = run(["G20 G91 G56 G19 G93 M4 S12.5 M7 T3", "M8 G1 F7"])
    assert interpreter.gc_report() == "[GC:G1 G56 G19 G20 G91 G93 M4 M7 M8 T3 F7 S12.5]"


def test_modal_snapshot_is_json_serialisable() -> None:
    interpreter, _ = run(["G20 G91 G55 M3 S100 M8 G1 F10"])
    snapshot = json.loads(json.dumps(interpreter.modal_snapshot()))
    assert snapshot["units"] == "in" and snapshot["distance"] == "incremental"
    assert snapshot["wcs"] == "G55" and snapshot["plane"] == "G17"
    assert snapshot["feed_mm_min"] == pytest.approx(254.0)
    assert snapshot["s"] == 100.0 and snapshot["tool_mode"] == "M3"
    assert snapshot["coolant"] == {"mist": False, "flood": True}


def test_reset_restores_power_on_modes_but_keeps_stored_offsets_and_position() -> None:
    interpreter, _ = run(["G10 L2 P1 X5", "G0 X10", "G28.1", "G92 X0", "G43.1 Z1",
                          "G20 G91 G55 M3 S100 M8 T2 G1 F10"])
    interpreter.reset()
    assert interpreter.gc_report() == "[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]"
    assert interpreter.position == (15.0, 0.0, 0.0)
    report = interpreter.offsets_report()
    assert report[0] == "[G54:5.000,0.000,0.000]" and report[6] == "[G28:15.000,0.000,0.000]"
    assert report[8] == "[G92:0.000,0.000,0.000]" and report[9] == "[TLO:0.000]"
    assert interpreter.wco() == (5.0, 0.0, 0.0)


def test_settings_reject_unknown_axes() -> None:
    with pytest.raises(ValueError):
        InterpreterSettings(("X", "E"), (0, 0), (1, 1))


def test_xy_machine_refuses_z_words_and_g43_1() -> None:
    interpreter = Interpreter(InterpreterSettings(("X", "Y"), (0, 0), (100, 100)))
    for text, code in (("G0 Z1", 20), ("G43.1 Z1", 20), ("G18 G2 X1 I1 F10", 20)):
        with pytest.raises(CommandError) as caught:
            interpreter.execute(parse_line(text))
        assert caught.value.code == code


def test_rotary_axes_are_not_scaled_by_g20() -> None:
    machine = InterpreterSettings(("X", "Y", "Z", "A"), (-500,) * 4, (500,) * 4)
    interpreter, _ = run(["G20 G0 X1 A90"], machine)
    assert interpreter.position == pytest.approx((25.4, 0, 0, 90))


# -- the fast path ---------------------------------------------------------------------------
SIMPLE_WORDS = st.lists(st.sampled_from(["G0", "G1", "X", "Y", "Z", "F", "S", "G20", "G21",
                                         "G90", "G91", "G93", "G94", "G55", "G92"]),
                        min_size=1, max_size=5)


def line_from(tokens: list[str], values: list[float]) -> str:
    parts = []
    for token, value in zip(tokens, values, strict=False):
        parts.append(token if token.startswith("G") else f"{token}{value:.3f}")
    return " ".join(parts)


class GeneralOnly(Interpreter):
    """The interpreter with its fast path switched off."""

    def _fast_line(self, line: Line) -> list[Output] | None:
        return None


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(SIMPLE_WORDS, st.lists(st.floats(-40, 400), min_size=5,
                                                  max_size=5)), min_size=1, max_size=12))
def test_fast_path_gives_the_same_outputs_errors_and_state_as_the_general_path(
        program: list[tuple[list[str], list[float]]]) -> None:
    fast, general = Interpreter(SMALL), GeneralOnly(SMALL)
    for tokens, values in program:
        line = parse_line(line_from(tokens, values))
        results: list[list[Output] | int] = []
        for interpreter in (fast, general):
            try:
                results.append(interpreter.execute(line))
            except CommandError as error:
                results.append(error.code)
        assert results[0] == results[1]
        assert state_of(fast) == state_of(general)
