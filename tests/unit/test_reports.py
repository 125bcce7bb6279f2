"""Grbl report formatting: exact text, field by field, and the WCO/Ov schedule."""

from __future__ import annotations

import dataclasses

import pytest

from server.errors import ALARM_MEANINGS, ERROR_MEANINGS
from server.protocol.lines import LineProtocol
from server.protocol.reports import (
    StatusScheduler,
    StatusSnapshot,
    format_alarm,
    format_build_info,
    format_help,
    format_position_m114,
    format_reprap_error,
    format_settings,
    format_status,
    sender_blocks,
)

IDLE = StatusSnapshot(
    state="Idle",
    machine_mm=(0.0, 0.0, 0.0),
    wco_mm=(0.0, 0.0, 0.0),
    feed_mm_s=0.0,
    spindle_s=0.0,
    planner_free_blocks=15,
    rx_free_bytes=128,
    line_number=None,
    pins="",
    overrides=(100, 100, 100),
    accessories="",
)


def snap(**changes: object) -> StatusSnapshot:
    return dataclasses.replace(IDLE, **changes)


# -- status report --------------------------------------------------------------------------


def test_idle_report_with_grbl_default_mask() -> None:
    assert format_status(IDLE) == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>"


def test_buffer_field_follows_the_position_when_mask_bit_1_is_set() -> None:
    report = format_status(IDLE, report_mask=3)
    assert report == "<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0>"


def test_work_position_is_machine_minus_offset_when_mask_bit_0_is_clear() -> None:
    report = format_status(
        snap(machine_mm=(10.0, 5.0, -1.0), wco_mm=(2.5, 0.0, -1.0)), report_mask=0
    )
    assert report == "<Idle|WPos:7.500,5.000,0.000|FS:0,0>"


def test_positions_have_three_decimals_and_never_print_negative_zero() -> None:
    report = format_status(snap(machine_mm=(1.23456, -0.0001, -12.3456)))
    assert "MPos:1.235,0.000,-12.346|" in report


def test_line_number_appears_only_when_set() -> None:
    assert "|Ln:42|" in format_status(snap(line_number=42))
    assert "Ln:" not in format_status(snap(line_number=None))
    assert "Ln:" not in format_status(snap(line_number=0))


def test_feed_is_reported_in_mm_per_minute_and_spindle_without_decimals() -> None:
    report = format_status(snap(state="Run", feed_mm_s=25.0, spindle_s=12000.4))
    assert report == "<Run|MPos:0.000,0.000,0.000|FS:1500,12000>"


def test_inches_give_four_decimals_and_inches_per_minute() -> None:
    report = format_status(
        snap(machine_mm=(25.4, 2.54, 0.0), wco_mm=(25.4, 0.0, 0.0), feed_mm_s=25.4),
        inches=True,
        include_wco=True,
    )
    assert report == "<Idle|MPos:1.0000,0.1000,0.0000|FS:60.0,0|WCO:1.0000,0.0000,0.0000>"


def test_pins_appear_only_when_some_are_triggered() -> None:
    assert format_status(snap(pins="XP")).endswith("|FS:0,0|Pn:XP>")
    assert "Pn:" not in format_status(IDLE)


def test_overrides_carry_the_accessories_only_when_some_are_on() -> None:
    report = format_status(snap(overrides=(120, 50, 80), accessories="SF"), include_ov=True)
    assert report.endswith("|Ov:120,50,80|A:SF>")
    assert format_status(IDLE, include_ov=True).endswith("|Ov:100,100,100>")
    assert "A:" not in format_status(snap(accessories="SF"))


def test_all_fields_come_in_grbl_order() -> None:
    full = snap(
        state="Hold:1",
        machine_mm=(1.0, 2.0, 3.0),
        wco_mm=(0.5, 0.5, 0.5),
        feed_mm_s=10.0,
        spindle_s=500.0,
        planner_free_blocks=3,
        rx_free_bytes=60,
        line_number=7,
        pins="Z",
        overrides=(100, 25, 100),
        accessories="CFM",
    )
    report = format_status(full, report_mask=3, include_wco=True, include_ov=True)
    assert report == (
        "<Hold:1|MPos:1.000,2.000,3.000|Bf:3,60|Ln:7|FS:600,500|Pn:Z"
        "|WCO:0.500,0.500,0.500|Ov:100,25,100|A:CFM>"
    )


def test_status_reports_and_alarms_are_pushable() -> None:
    protocol = LineProtocol()
    full = snap(state="Check", pins="P", accessories="S", line_number=3)
    protocol.push(format_status(full, report_mask=3, include_wco=True, include_ov=True))
    for code in ALARM_MEANINGS:
        protocol.push(format_alarm(code))


# -- WCO / Ov schedule ----------------------------------------------------------------------


def schedule_indices(snapshot: StatusSnapshot, reports: int) -> tuple[list[int], list[int]]:
    scheduler = StatusScheduler()
    wco, ov = [], []
    for index in range(reports):
        include_wco, include_ov = scheduler.schedule(snapshot)
        if include_wco:
            wco.append(index)
        if include_ov:
            ov.append(index)
    return wco, ov


def test_idle_machine_refreshes_wco_and_ov_every_ten_reports_never_together() -> None:
    wco, ov = schedule_indices(IDLE, 40)
    assert wco == [0, 10, 20, 30]
    assert ov == [1, 11, 21, 31]


@pytest.mark.parametrize("state", ["Run", "Hold:0", "Jog", "Home", "Door:1"])
def test_busy_machine_refreshes_wco_every_thirty_and_ov_every_twenty(state: str) -> None:
    wco, ov = schedule_indices(snap(state=state), 70)
    assert wco == [0, 30, 60]
    assert ov == [1, 21, 41, 61]


def test_changed_work_offset_is_sent_in_the_next_report() -> None:
    scheduler = StatusScheduler()
    for _ in range(5):
        scheduler.schedule(IDLE)
    assert scheduler.schedule(snap(wco_mm=(1.0, 0.0, 0.0))) == (True, False)
    assert scheduler.schedule(snap(wco_mm=(1.0, 0.0, 0.0))) == (False, False)


@pytest.mark.parametrize("change", [{"overrides": (110, 100, 100)}, {"accessories": "M"}])
def test_changed_overrides_or_accessories_are_sent_in_the_next_report(change: dict) -> None:
    scheduler = StatusScheduler()
    for _ in range(5):
        scheduler.schedule(IDLE)
    assert scheduler.schedule(snap(**change)) == (False, True)
    assert scheduler.schedule(snap(**change)) == (False, False)


def test_refresh_sends_both_fields_again() -> None:
    scheduler = StatusScheduler()
    for _ in range(5):
        scheduler.schedule(IDLE)
    scheduler.refresh()
    assert scheduler.schedule(IDLE) == (True, False)
    assert scheduler.schedule(IDLE) == (False, True)


def test_scheduler_report_formats_on_schedule() -> None:
    scheduler = StatusScheduler()
    assert scheduler.report(IDLE).endswith("|WCO:0.000,0.000,0.000>")
    assert scheduler.report(IDLE, report_mask=2).endswith("|Bf:15,128|FS:0,0|Ov:100,100,100>")
    assert scheduler.report(IDLE) == "<Idle|MPos:0.000,0.000,0.000|FS:0,0>"


# -- $ commands -----------------------------------------------------------------------------


def test_settings_are_sorted_ints_plain_and_floats_with_three_decimals() -> None:
    values = {110: 5000.0, 0: 10, 11: 0.01, 32: True, 1: 25, 30: 1000}
    assert format_settings(values) == [
        "$0=10",
        "$1=25",
        "$11=0.010",
        "$30=1000",
        "$32=1",
        "$110=5000.000",
    ]


def test_help_is_grbl_1_1_help_line() -> None:
    assert (
        format_help() == "[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]"
    )


def test_free_blocks_are_on_grbls_scale_empty_only_when_the_planner_is() -> None:
    assert sender_blocks(4096, 4096) == 15 and sender_blocks(4095, 4096) == 14
    assert sender_blocks(0, 4096) == 0 and sender_blocks(272, 4096) == 0
    assert sender_blocks(7, 8) == 7 and sender_blocks(-3, 8) == 0


def test_build_info_has_version_and_options_with_buffer_sizes() -> None:
    assert format_build_info("motiond", 15, 128) == ["[VER:1.1h.motiond:]", "[OPT:VL,15,128]"]
    assert format_build_info("20240101", 31, 1024, build_info="laser", options="VNM") == [
        "[VER:1.1h.20240101:laser]",
        "[OPT:VNM,31,1024]",
    ]


def test_build_info_keeps_a_version_that_already_starts_with_the_grbl_version() -> None:
    assert format_build_info("1.1h.motiond-0.1.0", 15, 128)[0] == "[VER:1.1h.motiond-0.1.0:]"


def test_alarms_are_numbered_lines_with_a_meaning_for_every_code() -> None:
    assert format_alarm(1) == "ALARM:1"
    assert set(range(1, 11)) <= set(ALARM_MEANINGS)
    assert all(text for text in ALARM_MEANINGS.values())


def test_every_documented_error_code_has_a_meaning() -> None:
    documented = [1, 2, 3, 4, 5, 8, 9, 10, 11, 15, 16, *range(20, 39), *range(40, 47)]
    assert all(ERROR_MEANINGS[code] for code in documented)


# -- RepRap error wording ------------------------------------------------------------------


def test_reprap_communication_errors_use_marlins_exact_resend_lines() -> None:
    assert format_reprap_error(41, "whatever", 9) == [
        "Error:checksum mismatch, Last Line: 9",
        "Resend: 10",
        "ok",
    ]
    assert format_reprap_error(42, "", -1)[0] == (
        "Error:Line Number is not Last Line Number+1, Last Line: -1"
    )


def test_reprap_unknown_command_falls_back_to_the_description_without_a_message() -> None:
    assert format_reprap_error(20, "", 0) == [
        "echo:Unsupported or invalid G-code command (code 20)",
        "ok",
    ]


# -- M114 -----------------------------------------------------------------------------------


def test_m114_reports_the_work_position_like_smoothie() -> None:
    text = format_position_m114((11.0, 22.5, -3.0), (1.0, 2.5, -3.0), ("X", "Y", "Z"))
    assert text == "C: X:1.0000 Y:2.5000 Z:-3.0000"


def test_m114_subcodes_give_work_and_machine_positions() -> None:
    machine, work = (11.0, 22.5, 0.0), (1.0, 2.5, 0.0)
    assert format_position_m114(machine, work, subcode=1) == "WCS: X:1.0000 Y:2.5000 Z:0.0000"
    assert format_position_m114(machine, work, subcode=2) == "MCS: X:11.0000 Y:22.5000 Z:0.0000"


def test_m114_in_inches_and_with_more_axes() -> None:
    text = format_position_m114((0.0,) * 4, (25.4, 0.0, 0.0, 12.7), "XYZA", inches=True)
    assert text == "C: X:1.0000 Y:0.0000 Z:0.0000 A:0.5000"


def test_every_error_and_alarm_number_has_one_meaning_in_the_one_table() -> None:
    from server.errors import ALARM_MEANINGS, ERROR_MEANINGS, Alarm, CommandError, Error

    assert set(ERROR_MEANINGS) == set(Error) and set(ALARM_MEANINGS) == set(Alarm)
    with pytest.raises(ValueError):
        CommandError(39, "a number outside the table is a bug")


def test_a_misspelt_event_name_is_refused_when_subscribing() -> None:
    from server.runtime.events import Event, EventBus

    bus = EventBus()
    seen: list[str] = []
    bus.subscribe("halt", seen.append)
    bus.emit(Event.HALT, "why")
    assert seen == ["why"]
    with pytest.raises(ValueError):
        bus.subscribe("hlat", seen.append)
