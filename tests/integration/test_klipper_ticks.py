"""#26, part T: ticks only when needed. On the Klipper backend the step generator samples the
backend when it next needs a sample (a run's turn to leave, steps due for generation, an
output's refresh; at most the hold-back and a flush apart), not every flush; what
must act at once (a hold, a halt) brings the next tick forward; an idle server wakes only for
its periodic jobs, all on one grid. Against the virtual MCU over a real pty, lead 0.3 s (the
default: a hold-back of 0.15 s)."""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

from server.app import App
from server.backends.klipper.backend import SAMPLE_GAP_MAX_S, KlipperBackend
from server.motion.motion_state import HoldState
from tests.integration.test_klipper_faults import wait_for_alarm
from tests.support.helpers import submit_all
from tests.support.klipper_machine import klipper_machine
from tests.support.virtual_mcu import VirtualMcu

LEAD_S = 0.3
LASER = {"pin": "PA8"}


def klipper(app: App) -> KlipperBackend:
    backend = app.kernel.machine.backend
    assert isinstance(backend, KlipperBackend) and backend.mcu is not None
    return backend


def record_samples(backend: KlipperBackend) -> list[float]:
    """The monotonic times the backend is sampled at from now on."""
    times: list[float] = []
    sample = backend.sample

    def counted(time_s: float, position_mm: Any, speed_mm_s: float) -> None:
        times.append(time.monotonic())
        sample(time_s, position_mm, speed_mm_s)

    backend.sample = counted  # type: ignore[method-assign]
    return times


async def just_after_a_sample(samples: list[float]) -> None:
    """Wait for the next sample, then 10 ms: the sparse sample after it is far off."""
    seen = len(samples)
    for _ in range(500):
        if len(samples) > seen:
            break
        await asyncio.sleep(0.001)
    assert len(samples) > seen, "no sample within 0.5 s"
    await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def cruising(mcu: VirtualMcu) -> AsyncIterator[tuple[App, KlipperBackend, list[float]]]:
    """A 150 mm laser cut at 100 mm/s, 0.5 s in, 10 ms after a sample: the app, its backend
    and the times it is sampled at from then on."""
    async with klipper_machine(mcu, lead_time_s=LEAD_S, laser=LASER) as app:
        backend = klipper(app)
        await submit_all(app, ["M3 S800", "G1 X150 F6000"])
        await asyncio.sleep(0.5)
        samples = record_samples(backend)
        await just_after_a_sample(samples)
        yield app, backend, samples


@pytest.mark.slow
async def test_a_cruise_is_sampled_only_when_the_backend_needs_it(mcu: VirtualMcu) -> None:
    """100 mm/s along X for 1.5 s: in the cruise the backend is sampled about every 158 ms
    (each run's turn to leave, as late as a flush would send it), not every 20 ms flush (50 a
    second); every run still reaches the MCU at least the lead less the hold-back less a flush
    ahead (the ride-through the flushes kept), and every step is exact."""
    async with klipper_machine(mcu, lead_time_s=LEAD_S) as app:
        backend = klipper(app)
        samples = record_samples(backend)
        await submit_all(app, ["G1 X150 F6000"])  # cruising from 0.05 s to 1.45 s
        await asyncio.sleep(0.4)
        first, started = len(samples), time.monotonic()
        await asyncio.sleep(0.8)
        rate = (len(samples) - first) / (time.monotonic() - started)
        assert 1.0 / SAMPLE_GAP_MAX_S - 3.0 < rate < 12.0, f"{rate:.1f} samples/s (main: 50)"
        await app.kernel.machine.wait_idle()
        await asyncio.sleep(LEAD_S + 0.1)
        assert backend.mcu is not None and backend.mcu.clock is not None
        ahead_s = mcu.min_lead_ticks / backend.mcu.clock.freq_hz
        # less what the design cannot help: the loop's own late wake-ups (a flush would be as
        # late), and the virtual MCU, a thread of this interpreter, reading the block only
        # when the loop lets go of the interpreter lock (a switch interval at most)
        late_s = app.kernel.loop_monitor.worst_stall_s + sys.getswitchinterval()
        assert ahead_s > LEAD_S - backend.hold_back_s - backend.flush_s - late_s, (
            ahead_s, late_s)
        clocks, _ = mcu.step_clocks(backend.axes[0].oid)
        assert len(clocks) == 150 * 80 and backend.fault is None


async def test_a_raster_sampled_in_late_tick_slices_keeps_the_laser_on_along_its_line(
        mcu: VirtualMcu) -> None:
    """0.05 mm segments at 100 mm/s: a sample 75-158 ms after the last spans more blocks than
    a step generator call takes (the backend's 128), so it comes in slices, each ending on a
    block's end. Such a slice is not motion's end: the laser (M3, following the pieces) goes
    on once and off once, never off and on again in between; every step is exact."""
    async with klipper_machine(mcu, lead_time_s=LEAD_S,
                               laser={"pin": "PA8", "maximum_power": 0.8}) as app:
        backend, stepgen = klipper(app), app.kernel.machine.stepgen
        advance, sliced = stepgen.advance, [0]

        def counted(now_s: float) -> bool:
            done = advance(now_s)
            sliced[0] += not done
            return done

        stepgen.advance = counted  # type: ignore[method-assign]
        segments = [f"G1 X{0.05 * k:.2f}" for k in range(1, 601)]
        await submit_all(app, ["G0 X0 Y5", "M3 S500", "G1 F6000", *segments, "M5"])
        await app.kernel.machine.wait_idle()
        await asyncio.sleep(LEAD_S + 0.1)
        assert sliced[0] >= 2, "the samples came in slices"
        assert backend.pwm_log is not None
        values = [value for _, name, value, _ in backend.pwm_log if name == "PA8"]
        assert values == [0.4, 0.0], values
        assert [value for _, value in mcu.output_events("PA8")[1:]] == [102, 0]
        clocks, _ = mcu.step_clocks(backend.axes[0].oid)
        assert len(clocks) == 600 * 4 and backend.fault is None


async def test_a_hold_between_sparse_samples_decelerates_and_turns_the_laser_off_at_once(
        mcu: VirtualMcu) -> None:
    """A feed hold 10 ms after a sample (the next sparse one ~155 ms away): the step generator
    is ticked at once, the deceleration starts where the steps reached (no later than the
    command on the motion's timeline) and the laser's off is queued then; the machine stops
    within the deceleration distance, every step sent executed."""
    async with cruising(mcu) as (app, backend, samples):
        machine = app.kernel.machine
        assert backend.pwm_log is not None
        logged = len(backend.pwm_log)
        hold_s, before = time.monotonic(), len(samples)
        app.kernel.control.hold()
        await asyncio.sleep(0.03)
        assert len(samples) > before and samples[before] - hold_s < 0.025, "ticked at once"
        offs = [when_s for when_s, name, value, _ in backend.pwm_log[logged:]
                if name == "PA8" and value == 0.0]
        assert offs and offs[0] <= hold_s, "the laser goes off where the deceleration starts"
        for _ in range(100):
            if machine.stepgen.state.hold is HoldState.STOPPED:
                break
            await asyncio.sleep(0.01)
        assert machine.stepgen.state.hold is HoldState.STOPPED
        stop_mm = machine.stepgen.state.position_mm[0]
        await asyncio.sleep(LEAD_S + 0.1)
        clocks, _ = mcu.step_clocks(backend.axes[0].oid)
        assert len(clocks) == round(stop_mm * 80) and backend.fault is None
        assert mcu.output_events("PA8")[-1][1] == 0


async def test_a_halt_between_sparse_samples_stops_the_board_at_once(mcu: VirtualMcu) -> None:
    """Ctrl-X 10 ms after a sample: the emergency stop reaches the MCU within a few ms (not
    at the next sample), and the ticks stop at once (the link is read as data arrives)."""
    async with cruising(mcu) as (app, backend, _):
        halt_s = time.monotonic()
        app.kernel.control.reset()
        took_s = await until(lambda: bool(mcu.shutdowns), 1.0)
        assert mcu.shutdowns == ["Command request"] and took_s < 0.05, took_s
        assert mcu.output_events("PA8")[-1][1] == 0
        assert backend.mcu is not None
        link = backend.mcu.link
        await until(lambda: not link.sampling, 1.0)
        assert time.monotonic() - halt_s < SAMPLE_GAP_MAX_S, "the ticks rest at once"


async def test_a_board_shutdown_mid_cruise_is_read_within_the_longest_sample_gap(
        mcu: VirtualMcu) -> None:
    async with cruising(mcu) as (app, backend, _):
        with mcu.lock:
            mcu.shutdown("Rescheduled timer in the past")
        took_s = await wait_for_alarm(app)
        assert took_s < SAMPLE_GAP_MAX_S + 0.05, f"{took_s * 1e3:.0f} ms"
        assert "Rescheduled timer in the past" in app.kernel.alarm_message
        assert backend.fault is not None


@pytest.mark.slow
async def test_an_idle_server_wakes_only_for_its_periodic_jobs_on_one_grid(
        mcu: VirtualMcu) -> None:
    """Quiet and idle (the steps done, no command for a second): the event loop's timers wake
    it twice a second, for the MCU's clock poll, the loop monitor and the kernel's second
    together (main: about 7 times, each on its own), plus the reads of each answer."""
    async with klipper_machine(mcu, lead_time_s=LEAD_S) as app:
        await submit_all(app, ["G1 X5 F6000"])
        await app.kernel.machine.wait_idle()
        await asyncio.sleep(1.5)  # the steps run out, then a quiet second
        assert app.kernel.machine.stepgen.can_sleep
        selector = asyncio.get_running_loop()._selector  # type: ignore[attr-defined]
        select = selector.select
        wakes, by_timer = [0], [0]

        def counted(timeout: float | None = None) -> Any:
            events = select(timeout)
            if timeout is None or timeout > 0.0:  # the loop slept: a wake-up
                wakes[0] += 1
                by_timer[0] += not events  # no device ready: a timer's deadline woke it
            return events

        selector.select = counted
        try:
            await asyncio.sleep(3.0)
        finally:
            selector.select = select
        assert by_timer[0] / 3.0 <= 3.0, f"{by_timer[0] / 3.0:.1f} timer wake-ups/s (main: 7)"
        assert wakes[0] / 3.0 <= 8.0, f"{wakes[0] / 3.0:.1f} wake-ups/s (main: 9.5)"


async def until(condition: Callable[[], bool], limit_s: float) -> float:
    """Seconds until ``condition()`` holds (fails after ``limit_s``)."""
    start = time.monotonic()
    while not condition():
        assert time.monotonic() - start < limit_s, "never"
        await asyncio.sleep(0.001)
    return time.monotonic() - start


async def test_a_host_hung_past_the_silence_limit_reads_the_board_s_shutdown_first(
        mcu: VirtualMcu) -> None:
    """motiond hangs 1.2 s mid-cut (past the MCU's silence limit, 0.5 s + a poll): the board's
    watchdog turns the laser off and it shuts down. Once the host runs again, what the board
    said is read before its silence is judged: the alarm is the board's shutdown (or the late
    steps), never "stopped answering"."""
    async with klipper_machine(mcu, lead_time_s=LEAD_S, max_duration_s=0.3,
                               laser=LASER) as app:
        await submit_all(app, ["M3 S800", "G1 X100 F1200"])
        await asyncio.sleep(0.6)
        time.sleep(1.2)  # noqa: ASYNC251 - motiond hangs, on purpose
        await wait_for_alarm(app)
        assert mcu.shutdowns[:1] == ["Missed scheduling of next hard pwm event"]
        assert mcu.output_events("PA8")[-1][1] == 0, "the board turned the laser off"
        message = app.kernel.alarm_message
        assert "stopped answering" not in message, message
        assert any(why in message for why in ("Missed", "not sent in time")), message
