"""[klippy_api]'s pure parts: the socket framing, Klipper's G-code translated, the printer
objects from a status snapshot, and the change-only subscription diff."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest

from modules.klippy_api import objects, outputs, wire
from modules.klippy_api.gcode import (
    Control,
    FeedOverride,
    GcodeOffset,
    Line,
    Message,
    StartJob,
    check_line_during_job,
    klipper_error,
    translate,
)
from modules.klippy_api.session import response_text
from server.errors import CommandError, Error

JOG_FEED = 30000.0
MACHINE = objects.Machine((0.0, 0.0, -50.0), (400.0, 300.0, 0.0), 500.0, 3000.0,
                          Path("/srv/jobs"), frozenset({"x", "y"}))


def status(**changes: Any) -> dict[str, Any]:
    base: dict[str, Any] = {
        "state": "Idle", "alarm": None, "mpos": [10.0, 20.0, 0.0], "wpos": [5.0, 20.0, 0.0],
        "wco": [5.0, 0.0, 0.0], "speed_mm_min": 600.0, "moving": False,
        "overrides": {"feed": 100, "rapid": 100, "spindle": 100},
        "modal": {"distance": "absolute", "feed_mm_min": 1200.0},
        "job": None, "modules": {"endstops": {"homed": []}},
    }
    return base | changes


def test_framer_returns_whole_requests_split_anywhere() -> None:
    framer = wire.Framer()
    data = wire.encode({"id": 1, "method": "info", "params": {}}) + wire.encode(
        {"id": 2, "method": "objects/list"})
    assert framer.feed(data[:5]) == []
    requests = framer.feed(data[5:])
    assert [(r.id, r.method) for r in requests] == [(1, "info"), (2, "objects/list")]


def test_framer_refuses_a_request_larger_than_its_bound() -> None:
    framer = wire.Framer(limit_bytes=100)
    with pytest.raises(wire.FramingError):
        framer.feed(b"{" + b" " * 200)


def test_framer_refuses_what_is_not_a_json_object() -> None:
    with pytest.raises(wire.FramingError):
        wire.Framer().feed(b"[1, 2]\x03")
    with pytest.raises(wire.FramingError):
        wire.Framer().feed(b"{nope\x03")


def test_encode_ends_with_etx_and_refuses_nan() -> None:
    assert wire.encode({"id": 1, "result": {}}).endswith(b"\x03")
    assert json.loads(wire.encode({"a": 1})[:-1]) == {"a": 1}
    with pytest.raises(ValueError):
        wire.encode({"a": float("nan")})


def test_sdcard_print_file_starts_the_named_job_with_quotes_and_slash_removed() -> None:
    assert translate('SDCARD_PRINT_FILE FILENAME="my \\"part\\".gcode"', JOG_FEED) == [
        StartJob('my "part".gcode')]
    assert translate("SDCARD_PRINT_FILE FILENAME=/a.nc", JOG_FEED) == [StartJob("a.nc")]


def test_g28_homes_all_or_the_named_axes_with_motiond_homing() -> None:
    assert translate("G28", JOG_FEED) == [Line("G28.2")]
    assert translate("G28 X Y", JOG_FEED) == [Line("G28.2 X0 Y0")]
    assert translate("g28 z", JOG_FEED) == [Line("G28.2 Z0")]


def test_feed_override_from_m220_and_set_velocity_factor() -> None:
    assert translate("M220 S150", JOG_FEED) == [FeedOverride(150)]
    assert translate("SET_VELOCITY_FACTOR FACTOR=0.5", JOG_FEED) == [FeedOverride(50)]
    with pytest.raises(CommandError):
        translate("SET_VELOCITY_FACTOR FACTOR=nan", JOG_FEED)


def test_mainsail_jog_sequence_becomes_one_jog() -> None:
    script = ("SAVE_GCODE_STATE NAME=_ui_movement\nG91\nG1 X10 F6000\n"
              "RESTORE_GCODE_STATE NAME=_ui_movement")
    assert translate(script, JOG_FEED) == [Line("$J=G21 G91 X10 F6000")]


def test_jog_sequence_without_save_keeps_its_trailing_g90() -> None:
    assert translate("G91\nG0 Y-5 F1200\nG90", JOG_FEED) == [
        Line("$J=G21 G91 Y-5 F1200"), Line("G90")]


def test_client_linear_move_is_a_jog_relative_or_absolute() -> None:
    assert translate("_CLIENT_LINEAR_MOVE X=-1 Z=0.5 F=600", JOG_FEED) == [
        Line("$J=G21 G91 X-1 Z0.5 F600")]
    assert translate("_CLIENT_LINEAR_MOVE X=50 Y=60 F=3000 ABSOLUTE=1", JOG_FEED) == [
        Line("$J=G21 G90 X50 Y60 F3000")]
    assert translate("_CLIENT_LINEAR_MOVE Y=2", JOG_FEED) == [Line("$J=G21 G91 Y2 F30000")]
    with pytest.raises(CommandError):
        translate("_CLIENT_LINEAR_MOVE E=5 F=300", JOG_FEED)


def test_save_gcode_state_outside_a_jog_is_refused_not_ignored() -> None:
    with pytest.raises(CommandError):
        translate("SAVE_GCODE_STATE NAME=x\nG1 X5\nM5", JOG_FEED)


def test_job_controls_messages_and_plain_gcode() -> None:
    assert translate("PAUSE\nRESUME\nCANCEL_PRINT\nM112\nHELP\nFIRMWARE_RESTART", JOG_FEED) == [
        Control("pause"), Control("resume"), Control("cancel"), Control("estop"),
        Control("help"), Control("restart")]
    assert translate("M117 Hello there", JOG_FEED) == [Message("Hello there")]
    assert translate("G1 X5 F600\nM84\n$$", JOG_FEED) == [
        Line("G1 X5 F600"), Line("M84"), Line("$$")]


def test_webhooks_soft_limit_alarm_is_ready_but_emergency_stop_is_shutdown() -> None:
    soft = status(alarm={"code": 2, "message": "soft limit", "meaning": "Soft limit"})
    halt = status(alarm={"code": 40, "message": "M112", "meaning": "Emergency stop"})
    assert objects.webhooks(soft)["state"] == "ready"
    assert "ALARM:2" in objects.webhooks(soft)["state_message"]
    assert objects.webhooks(halt)["state"] == "shutdown"
    assert objects.webhooks(status())["state"] == "ready"


def test_objects_show_positions_offsets_and_feed_override() -> None:
    built = objects.build_objects(status(overrides={"feed": 150}), MACHINE, objects.Extra())
    assert built["toolhead"]["position"] == [10.0, 20.0, 0.0, 0.0]
    assert built["gcode_move"]["gcode_position"] == [5.0, 20.0, 0.0, 0.0]
    assert built["gcode_move"]["homing_origin"] == [5.0, 0.0, 0.0, 0.0]
    assert built["gcode_move"]["speed_factor"] == 1.5
    assert built["motion_report"]["live_velocity"] == 10.0
    assert built["configfile"]["config"]["virtual_sdcard"]["path"] == "/srv/jobs"
    assert set(built) == set(objects.OBJECT_NAMES)
    assert not any(name.startswith(("extruder", "heater", "output_pin")) for name in built)


def test_homed_axes_are_those_homed_and_those_without_a_switch() -> None:
    assert objects.homed_axes(status(), MACHINE) == "z"
    homed = status(modules={"endstops": {"homed": ["X", "Y"]}})
    assert objects.homed_axes(homed, MACHINE) == "xyz"


def test_a_two_axis_machine_has_no_z_stepper_and_homes_only_x_and_y() -> None:
    planar = dataclasses.replace(MACHINE, axes="xy")
    built = objects.build_objects(status(modules={"endstops": {"homed": ["X", "Y"]}}), planar,
                                  objects.Extra())
    assert built["toolhead"]["homed_axes"] == "xy"
    sections = built["configfile"]["settings"]
    assert "stepper_x" in sections and "stepper_z" not in sections


def test_unknown_extended_commands_and_velocity_limits_in_klippers_words() -> None:
    refused = CommandError(Error.BAD_NUMBER_FORMAT, "bad number after 'F'")
    assert klipper_error("foo_bar X=1", refused).message == 'Unknown command:"FOO_BAR"'
    assert klipper_error("G1 X1", refused) is refused  # a G-code line keeps motiond's error
    with pytest.raises(CommandError, match="Error on 'SET_VELOCITY_LIMIT ACCEL=500'"):
        translate("SET_VELOCITY_LIMIT ACCEL=500", JOG_FEED)
    assert translate("SET_VELOCITY_LIMIT", JOG_FEED) == [Control("velocity_limit")]


def test_print_stats_and_sdcard_follow_the_job() -> None:
    job = {"name": "a.nc", "state": "running", "lines_done": 25, "lines_total": 100,
           "elapsed_s": 3.0, "error": None}
    built = objects.build_objects(status(job=job), MACHINE, objects.Extra(file_size_bytes=4000))
    assert built["print_stats"]["state"] == "printing"
    assert built["print_stats"]["filename"] == "a.nc"
    assert built["virtual_sdcard"]["progress"] == 0.25
    assert built["virtual_sdcard"]["file_position"] == 1000
    assert built["virtual_sdcard"]["file_path"] == "/srv/jobs/a.nc"
    assert built["idle_timeout"]["state"] == "Printing"
    failed = objects.print_stats(job | {"state": "failed", "error": "line 3: error:2"})
    assert failed["state"] == "error" and "line 3" in failed["message"]
    assert objects.print_stats(job | {"state": "aborted"})["state"] == "cancelled"


def test_query_selects_fields_and_answers_unknown_objects_empty() -> None:
    built = objects.build_objects(status(), MACHINE, objects.Extra())
    picked = objects.select(built, {"toolhead": ["homed_axes"], "heater_bed": None})
    assert picked == {"toolhead": {"homed_axes": "z"}, "heater_bed": {}}


def test_diff_keeps_only_changed_fields() -> None:
    before = {"toolhead": {"position": [0, 0, 0, 0], "homed_axes": "xyz"}, "webhooks": {"a": 1}}
    after = {"toolhead": {"position": [1, 0, 0, 0], "homed_axes": "xyz"}, "webhooks": {"a": 1}}
    assert objects.diff(before, after) == {"toolhead": {"position": [1, 0, 0, 0]}}
    assert objects.diff(after, after) == {}


def test_job_times_leave_pauses_out_of_the_print_duration() -> None:
    times = objects.JobTimes()
    times.update("a.nc", 10.0, "running", 10.0)
    times.update("a.nc", 10.0, "paused", 12.0)
    assert times.durations(15.0) == (5.0, 2.0)
    times.update("a.nc", 10.0, "running", 16.0)
    times.update("a.nc", 10.0, "done", 20.0)
    assert times.durations(99.0) == (10.0, 6.0)
    times.update("b.nc", 50.0, "running", 50.0)
    assert times.durations(51.0) == (1.0, 1.0)


def test_replies_read_as_klipper_console_lines() -> None:
    assert response_text("[MSG:Caution: Unlocked]") == "// Caution: Unlocked"
    assert response_text("ALARM:2") == "!! ALARM:2"
    assert response_text("C: X:1.0000 Y:2.0000 Z:0.0000") == "X:1.0000 Y:2.0000 Z:0.0000"
    assert response_text("ok-ish text") == "ok-ish text"


def test_set_gcode_offset_parses_absolute_adjust_and_move() -> None:
    assert translate("SET_GCODE_OFFSET Z_ADJUST=0.05 MOVE=1", JOG_FEED) == [
        GcodeOffset({}, {"Z": 0.05}, True, None)]
    assert translate("SET_GCODE_OFFSET X=1 Y=-2", JOG_FEED) == [
        GcodeOffset({"X": 1.0, "Y": -2.0}, {}, False, None)]
    with pytest.raises(CommandError):
        translate("SET_GCODE_OFFSET E=1", JOG_FEED)


def test_progress_follows_motiond_planned_time_so_time_left_is_motiond_s() -> None:
    job = {"name": "a.nc", "state": "running", "lines_done": 90, "lines_total": 100,
           "remaining_s": 240.0, "error": None}
    extra = objects.Extra(file_size_bytes=1000, durations_s=(61.0, 60.0))
    built = objects.build_objects(status(job=job), MACHINE, extra)
    progress = built["virtual_sdcard"]["progress"]
    assert progress == 0.2 and built["display_status"]["progress"] == 0.2
    assert 60.0 / progress - 60.0 == pytest.approx(240.0)  # the front-ends' time left


def test_laser_and_switches_are_output_pins_switched_by_their_own_lines() -> None:
    modules = {"laser": {"power": 0.25}, "switch.air": {
        "pin": "air", "value": 1.0, "on_gcode": "M8", "off_gcode": "M9", "level_gcode": None,
        "max_s": 255.0}, "switch.fan": {"pin": "fan", "value": 0.5, "on_gcode": "M106",
                                       "off_gcode": "M107", "level_gcode": "M106 S",
                                       "max_s": 255.0}}
    built = objects.build_objects(status(modules=modules), MACHINE, objects.Extra())
    assert built["output_pin laser"] == {"value": 0.25} and built["output_pin air"]["value"] == 1
    settings = built["configfile"]["settings"]
    assert settings["output_pin air"]["pwm"] is False and settings["output_pin fan"]["pwm"]
    state = status(modules=modules)
    assert outputs.set_pin_line(state, "air", 1.0) == "M8"
    assert outputs.set_pin_line(state, "air", 0.0) == "M9"
    assert outputs.set_pin_line(state, "fan", 0.5) == "M106 S127.5"
    for pin, value in (("laser", 1.0), ("nozzle", 1.0), ("fan", 2.0)):
        with pytest.raises(CommandError):
            outputs.set_pin_line(state, pin, value)


def test_a_paused_job_refuses_every_console_line_a_running_one_its_motion() -> None:
    for line in ("M114", "G90 G1 X10", "$J=G91 X1 F100"):
        with pytest.raises(CommandError, match="the job is paused"):
            check_line_during_job(line, "paused")
    for line in ("G90 G1 X10", "$J=G91 X1 F100", "G28.2 X0", "g0x1"):
        with pytest.raises(CommandError, match="the job is running"):
            check_line_during_job(line, "running")
    for line in ("M114", "G4 P1", "G10 L20 P1 X0", "M8"):
        check_line_during_job(line, "running")
    check_line_during_job("G1 X10", "done")
