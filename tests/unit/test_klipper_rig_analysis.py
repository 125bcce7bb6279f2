"""The analysis of ``python -m benchmarks klipper``: pin edges against the ideal trapezoid (step
error, cruise ppm), the firmware's clock slips, and the blocks on the wire."""

from __future__ import annotations

import math
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from benchmarks import klipper_rig_analysis as analysis
from benchmarks.bench_klipper import done_after_ms, inexact_where
from benchmarks.klipper_rig_analysis import FREQ_HZ, Block, SerialLog, Trapezoid
from benchmarks.klipper_rig_hosts import threads
from tests.support.klipper_rig import GpioLog
from tests.support.rigs import KLIPPER_AVR, msgproto

MOVE = Trapezoid(distance_mm=20.0, speed_mm_s=100.0, accel_mm_s2=2000.0)


def test_the_ideal_trapezoid_accelerates_cruises_and_stops_where_it_should() -> None:
    times = analysis.ideal_times(MOVE, 80.0)
    assert times.size == 1600
    assert MOVE.accel_mm == pytest.approx(2.5) == MOVE.decel_mm
    assert MOVE.duration_s == pytest.approx(0.25)
    assert times[0] == pytest.approx(np.sqrt(2 * (0.5 / 80) / 2000))  # the first half step
    assert np.diff(times)[800] == pytest.approx(1 / 8000)  # cruise: 8,000 steps/s
    assert times[-1] == pytest.approx(0.25 - np.sqrt(2 * (0.5 / 80) / 2000))
    short = Trapezoid(0.1, 100.0, 2000.0)  # never reaches the speed: a triangle
    assert short.peak_mm_s == pytest.approx(np.sqrt(200.0))
    assert analysis.ideal_times(short, 80.0).size == 8
    corner = Trapezoid(20.0, 100.0, 2000.0, start_mm_s=10.0, end_mm_s=20.0)  # from a corner
    times = analysis.ideal_times(corner, 80.0)
    assert corner.accel_mm == pytest.approx((100**2 - 10**2) / 4000)
    assert times[0] == pytest.approx((np.sqrt(100 + 4000 * 0.5 / 80) - 10) / 2000)
    assert corner.duration_s - times[-1] == pytest.approx(
        (np.sqrt(400 + 4000 * 0.5 / 80) - 20) / 2000)


def test_edges_on_the_ideal_profile_have_no_error_whenever_the_move_starts() -> None:
    ideal = analysis.ideal_times(MOVE, 80.0)
    edges = np.round(ideal * FREQ_HZ) + 123_456_789
    errors = analysis.step_errors(edges, ideal)
    assert np.abs(errors).max() < 0.05  # µs: the rounding to a cycle
    assert analysis.cruise_ppm(edges, MOVE, 80.0) == pytest.approx(0.0, abs=1.0)


def test_a_late_step_and_a_slow_cruise_are_measured() -> None:
    ideal = analysis.ideal_times(MOVE, 80.0)
    edges = ideal * FREQ_HZ
    late = edges.copy()
    late[700] += 30e-6 * FREQ_HZ
    assert np.abs(analysis.step_errors(late, ideal)).max() == pytest.approx(30.0, abs=0.01)
    slow = ideal * (1 + 500e-6) * FREQ_HZ  # the MCU's clock 500 ppm fast: the moves 500 ppm slow
    assert analysis.cruise_ppm(slow, MOVE, 80.0) == pytest.approx(-500.0, abs=1.0)
    errors = analysis.step_errors(slow, ideal)
    assert np.percentile(np.abs(errors), 99) > 50  # 500 ppm over 0.25 s: ±62 µs
    assert analysis.cruise_ppm(slow, Trapezoid(0.1, 100.0, 2000.0), 80.0) is None


def test_lost_timer_overflows_are_found_from_the_clock_responses_and_put_back() -> None:
    clocks = [(c, c - 4_000) for c in range(10_000, 1_000_000, 100_000)]  # in flight 4,000
    clocks += [(c, c - 4_000 - 65_536 + 500) for c in range(1_100_000, 2_000_000, 100_000)]
    slips = analysis.clock_slips(clocks)
    assert slips == [(1_100_000, 65_536)]
    ideal = analysis.ideal_times(MOVE, 80.0)
    edges = ideal * FREQ_HZ + 1_000
    slipped = edges.copy()
    slipped[900:] += 65_536  # the firmware's clock fell behind: later steps come later
    back, found = analysis.unslip(slipped, ideal)
    assert found == 1 and np.allclose(back, edges)
    late = edges.copy()
    late[900:] += 20_000  # a schedule 1 ms late is not a slip: it stays
    assert analysis.unslip(late, ideal)[1] == 0
    wrapped = [(c + (1 << 32), (c - 4_000) % (1 << 32)) for c, _ in clocks[:3]]
    assert analysis.clock_slips(wrapped) == []  # the 32-bit clock wraps, nothing slipped


def test_blocks_are_split_on_the_wire_and_a_resent_sequence_is_a_retransmission() -> None:
    first, second = analysis.encode_block(1, b"\x05"), analysis.encode_block(2, b"")
    damaged = bytearray(analysis.encode_block(3, b"\x07\x08"))
    damaged[2] ^= 1
    data = b"\x7e" + first + b"\x00\x13" + bytes(damaged) + second
    assert [block for _, block in analysis.split_blocks(data)] == [first, second]
    assert first == bytes([6, 0x11, 0x05]) + first[3:5] + b"\x7e"
    log = SerialLog(sent=[Block(100, 20, 1, ["a"]), Block(200, 20, 2, ["b"]),
                          Block(300, 20, 1, ["a"]), Block(310, 20, 2, ["b"]),
                          Block(400, 20, 3, ["queue_step"] * 3, [10, 400, 500]),
                          Block(500, 5, 3, [])])
    figures = log.window(150, 450)
    assert (figures.bytes, figures.blocks, figures.messages) == (80, 4, 6)
    assert figures.lone == 3 and figures.steps_per_run == 400
    assert figures.retransmitted == 2
    assert figures.by_name == {"a": 1, "b": 2, "queue_step": 3}
    assert log.window(450, 550).by_name == {"(ack)": 1}


@pytest.mark.skipif(not (KLIPPER_AVR / "klipper.dict").is_file(), reason="rig klipper-avr absent")
def test_the_serial_log_is_decoded_with_klippers_own_parser(tmp_path: Path) -> None:
    proto = msgproto()
    parser = proto.MessageParser()
    dictionary = (KLIPPER_AVR / "klipper.dict").read_bytes()
    parser.process_identify(dictionary, decompress=False)
    get_clock = bytes(parser.create_command("get_clock"))
    sent = analysis.encode_block(1, get_clock + get_clock)
    reply = analysis.encode_block(2, bytes(parser.create_command("clock clock=123456")))
    block = parser.encode_msgblock(1, list(get_clock + get_clock))  # Klipper's own framing
    assert bytes(block[:-2] + block[-2] + block[-1:]) == sent
    path = tmp_path / "serial.log"
    path.write_text(f"1000 R {sent[:4].hex()}\n1010 R {sent[4:].hex()}\n"
                    f"5000 W {reply.hex()}\n")
    log = analysis.read_serial_log(path, proto, dictionary)
    assert [(b.cycle, b.seq, b.messages) for b in log.sent] == [
        (1010, 1, ["get_clock", "get_clock"])]
    assert log.clocks == [(5000, 123_456)]


def test_the_raster_job_is_the_same_motion_for_both_hosts_and_its_moves_run_back_to_back() -> None:
    from benchmarks.klipper_rig_hosts import SQUARE_CORNER_MM_S  # noqa: PLC0415
    from benchmarks.klipper_rig_jobs import CORNER_MM_S, raster  # noqa: PLC0415

    job = raster(lines=2)
    assert job.steps(0) == (3200, 0) and job.steps(1) == (16, 16)
    assert sum(line.startswith("G1 X") for line in job.motiond) == 400 == sum(
        line.startswith("G1 X") for line in job.klippy)
    assert abs(CORNER_MM_S - SQUARE_CORNER_MM_S) < 1e-9  # motiond's 90° junction = klippy's
    starts = job.move_starts_s()
    x0, y0, x1 = job.moves["x"][0], job.moves["y"][0], job.moves["x"][1]
    assert starts["x"] == [0.0, pytest.approx(x0.duration_s + y0.duration_s)]
    assert starts["y"][1] == pytest.approx(starts["x"][1] + x1.duration_s)


def test_a_process_s_main_thread_is_counted_apart_from_its_other_threads() -> None:
    """The benchmark's per-thread figures, read from /proc for this process: a thread that
    sleeps 20 times runs at least 20 times among the others; the main thread's own work shows
    in its run time, not the other thread's sleeps."""
    before = threads(os.getpid())
    finish = threading.Event()
    slept = threading.Event()

    def sleeper() -> None:
        for _ in range(20):
            time.sleep(0.001)
        slept.set()
        finish.wait()  # alive when counted: a thread that ended is not

    thread = threading.Thread(target=sleeper)
    thread.start()
    try:
        assert slept.wait(5.0)
        busy_until = time.thread_time() + 0.02
        while time.thread_time() < busy_until:  # 20 ms of the main thread's own CPU
            pass
        used = threads(os.getpid()) - before
    finally:
        finish.set()
        thread.join()
    assert used.other_runs >= 20, used
    assert used.main_ns >= 15_000_000, used
    assert used.main_runs >= 1, used


def test_a_count_that_is_off_says_where_the_steps_lie_in_the_window() -> None:
    """A run that is not exact names how far its first and last steps are from the window's
    bounds: a step missed at its end, 0.25 ms after it, shows as a last step close to the end."""
    rises = np.array([0.1, 1.0, 2.0]) * FREQ_HZ
    where = inexact_where(rises, 0, int(2.0016 * FREQ_HZ))
    assert where == "first step 100.0 ms after the window's start, last 1.6 ms before its end"
    assert inexact_where(np.array([]), 0, 1) == "no step"


def test_done_after_counts_from_the_job_s_own_last_step_wherever_it_falls() -> None:
    """The host said done 7.5 ms after the job's last step (its clock 1 s = 1e9 ns per 20 M
    cycles); with a step more wanted, which came 2 ms after the window's end, -2 ms; the
    next job's first step, however soon after, does not count; too few steps: NaN."""
    sync = np.array([[0, 5_000_000_000], [200_000_000, 15_000_000_000]], dtype=np.float64)
    gpio = GpioLog(edges={"A0": [(int(1.0 * FREQ_HZ), 1), (int(1.0 * FREQ_HZ) + 40, 0)],
                          "A3": [(int(0.5 * FREQ_HZ), 1)]})
    end_ns = 6_000_000_000 + 7_500_000
    assert done_after_ms(gpio, sync, 0, end_ns, {"A0": 1, "A3": 1}) == pytest.approx(7.5)
    gpio.edges["A3"].append((int(1.0095 * FREQ_HZ), 1))  # 2 ms after the window's end
    assert done_after_ms(gpio, sync, 0, end_ns, {"A0": 1, "A3": 2}) == pytest.approx(-2.0)
    gpio.edges["A0"].append((int(1.05 * FREQ_HZ), 1))  # the next job's first step
    assert done_after_ms(gpio, sync, 0, end_ns, {"A0": 1, "A3": 2}) == pytest.approx(-2.0)
    assert done_after_ms(gpio, sync, 0, end_ns, {"A0": 1, "A3": 1}) == pytest.approx(7.5)
    assert math.isnan(done_after_ms(gpio, sync, 0, end_ns, {"A0": 3, "A3": 1}))


def test_the_clock_fit_is_checked_against_when_the_mcu_read_each_clock() -> None:
    """Each poll's clock is found in the rig's responses: read at the cycle its response left
    less its lag behind the cycle count (whole lost overflows aside); the fit's prediction of
    it against that cycle's host time. A poll the rig never answered is left out."""
    sync = np.array([[0, 1_000_000_000], [200_000_000, 11_000_000_000]], dtype=np.float64)
    slipped = 40_000_000 - analysis.SLIP_TICKS  # one lost overflow before the second read
    clocks = [(20_000_000 + 8_000, 20_000_000), (40_000_000 + 9_000, slipped)]
    lines = ["12:00:01 DEBUG motiond.klipper: clock 1.999000 2.001000 20000000 fit 2.000100",
             "12:00:02 INFO motiond: something else",
             f"12:00:03 DEBUG motiond.klipper: clock 2.999 3.001 {slipped} fit 2.996723",
             "12:00:04 DEBUG motiond.klipper: clock 3.999 4.001 123 fit 4.0"]
    found = analysis.clock_fit_errors(lines, clocks, sync)
    assert [sent for sent, _ in found] == [1.999, 2.999]
    assert found[0][1] == pytest.approx(0.1, abs=1e-6)
    assert found[1][1] == pytest.approx(-3.277, abs=1e-6)  # the fit did not know of the slip
