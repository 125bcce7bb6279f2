"""Motion time is MCU time: the steps' intervals come from the planned motion at the MCU's
nominal CLOCK_FREQ, never from the host's estimate of the MCU's clock (pure, virtual time).

The real planner, step generator and Klipper backend run on a virtual clock; the MCU side is
the clock fit (set as a running fit would be) and a sink that decodes every message sent.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmarks.bench_klipper_host import Listener, OfflineBackend
from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.printclock import PrintClock
from server.backends.klipper.stepcompress import StepCompressor
from server.config_loader import build_config
from server.motion.moves import Move, MoveKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator
from server.runtime.parts import planner_settings

CLOCK_HZ = 16_000_000
FORMATS = {"commands": {"queue_step oid=%c interval=%u count=%hu add=%hi": 2,
                        "set_next_step_dir oid=%c dir=%c": 3,
                        "reset_step_clock oid=%c clock=%u": 4,
                        "queue_pwm_out oid=%c clock=%u value=%hu": 5},
           "config": {"CLOCK_FREQ": CLOCK_HZ, "PWM_MAX": 255}}


class Sink:
    def __init__(self, dictionary: Dictionary) -> None:
        self.dictionary, self.messages = dictionary, []  # type: list[tuple[str, Any]]

        self.now_s, self.sent_s = 0.0, []  # type: float, list[float]

    def send(self, *messages: bytes) -> None:
        for message in messages:
            decoded = self.dictionary.decode(message)
            self.messages.extend(decoded)
            self.sent_s += [self.now_s] * len(decoded)


class FittedMcu:
    """What the backend reads of an MCU: its dictionary, the clock fit, its move queue."""

    def __init__(self, fitted_hz: float) -> None:
        self.dictionary = Dictionary(FORMATS)
        self.clock = ClockSync(CLOCK_HZ)
        self.clock.reset(0.0, 0)
        self.clock.freq_hz = fitted_hz  # what a fit of an MCU this far off the host says
        self.move_count = 1 << 30
        self.link = Sink(self.dictionary)


def run(moves: list[Move], fitted_hz: float, lead_time_s: float = 0.2,
        sink: Sink | None = None) -> list[tuple[str, Any]]:
    """Every message the backend sends for ``moves`` with the fit at ``fitted_hz``
    (``sink``: where they go, with the virtual time each was sent at)."""
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 300, "accel_mm_s2": 3000, "max_mm": 400}
            for a in "xy"}
    pins = {"x": {"step_pin": "PB13", "dir_pin": "PB12"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2"}}
    core = build_config({"axes": axes, "backend": {
        "kind": "klipper", "serial": "/dev/null", "axes": pins,
        "lead_time_s": lead_time_s}}).core
    backend = OfflineBackend(core)
    mcu = FittedMcu(fitted_hz)
    if sink is not None:
        mcu.link = sink
    backend.mcu, backend.ready = mcu, True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.oid, axis.compressor = oid, StepCompressor(backend.cfg.max_error_s * CLOCK_HZ)
    planner = Planner(planner_settings(core), (0.0, 0.0))
    stepgen = StepGenerator(planner, backend, (80.0, 80.0), Listener())
    for move in moves:
        planner.append(move)
    now_s = 0.0
    stepgen.tick(now_s)
    stepgen.request_start()
    while not stepgen.idle or now_s < 0.5:
        now_s += 0.001
        backend.now_s = mcu.link.now_s = now_s
        stepgen.tick(now_s)
    for _ in range(int(lead_time_s * 1000) + 200):  # past the lead: everything flushed
        now_s += 0.001
        backend.now_s = mcu.link.now_s = now_s
        stepgen.tick(now_s)
    return mcu.link.messages


def steps(messages: list[tuple[str, Any]]) -> list[tuple[int, int, int, int]]:
    return [(p["oid"], p["interval"], p["count"], p["add"]) for name, p in messages
            if name == "queue_step"]


JOB = [Move((100.0, 30.0), 200.0, MoveKind.FEED, ToolMode.OFF, 0.0),
       Move((20.0, 60.0), 150.0, MoveKind.FEED, ToolMode.OFF, 0.0),
       Move((0.0, 0.0), 250.0, MoveKind.FEED, ToolMode.OFF, 0.0)]


def test_a_clock_fit_off_by_1000_ppm_changes_no_step_interval() -> None:
    nominal = steps(run(JOB, CLOCK_HZ))
    assert len(nominal) > 10
    for ppm in (1000.0, -1000.0):
        assert steps(run(JOB, CLOCK_HZ * (1 + ppm * 1e-6))) == nominal, ppm


def test_the_direction_is_sent_only_at_reversals() -> None:
    """X goes +, -, - and Y +, +, -: each sets its direction twice (its first, one reversal)."""
    dirs = [(p["oid"], p["dir"]) for name, p in run(JOB, CLOCK_HZ)
            if name == "set_next_step_dir"]
    assert dirs == [(0, 1), (1, 1), (0, 0), (1, 0)]


def test_cruise_speed_in_mcu_ticks_is_the_commanded_speed() -> None:
    """A long X move at 200 mm/s (16,000 steps/s): 1,000 cruise steps take exactly
    1,000 × 1,000 ticks at 16 MHz, whatever the fit says."""
    messages = run([Move((300.0, 0.0), 200.0, MoveKind.FEED, ToolMode.OFF, 0.0)],
                   CLOCK_HZ * 1.001)
    clocks, last = [], 0
    for name, p in messages:
        if name == "reset_step_clock" and p["oid"] == 0:
            last = p["clock"]
        if name == "queue_step" and p["oid"] == 0:
            k = np.arange(p["count"], dtype=np.int64)
            clocks.append(last + (k + 1) * p["interval"] + p["add"] * (k * (k + 1) // 2))
            last = int(clocks[-1][-1])
    intervals = np.diff(np.concatenate(clocks))
    cruise = intervals[intervals.size // 2 - 5000:intervals.size // 2 + 5000]
    assert abs(cruise.mean() / 1000.0 - 1.0) < 5e-6  # within 5 ppm


def test_the_schedule_runs_at_nominal_until_it_drifts_then_follows_the_fit() -> None:
    """A fit 1,000 ppm off: nominal for the first 10 ms of drift, then steered back; the
    schedule never jumps and never strays beyond the bound by more than a flush's drift."""
    sched = PrintClock(CLOCK_HZ, 0.01)
    sched.anchor(0.0, 0.0)
    fitted_hz = CLOCK_HZ * 1.001
    previous, drifts = 0.0, []
    for k in range(1, 60 * 50 + 1):  # 60 s of flushes every 20 ms
        t = 0.02 * k
        before = float(sched.clock(t))
        sched.steer(t, fitted_hz * t, fitted_hz)
        assert float(sched.clock(t)) == before, "steering changes nothing already scheduled"
        assert before > previous
        previous = before
        drifts.append(sched.drift_s(t, fitted_hz * t))
        if t < 9.9:
            assert sched.hz == CLOCK_HZ
    assert max(abs(d) for d in drifts) < 0.0101
    assert sched.hz != CLOCK_HZ or abs(drifts[-1]) < 0.01


def first_step_leads_s(sink: Sink, oid: int) -> tuple[int, float]:
    """How many queue_step messages ``oid`` got, and the least time between sending one and
    its first step (the fit is exact from 0: clock / CLOCK_HZ is host time)."""
    runs, least_s, last = 0, float("inf"), 0
    for (name, p), sent_s in zip(sink.messages, sink.sent_s, strict=True):
        if p.get("oid") != oid:
            continue
        if name == "reset_step_clock":
            last = p["clock"]
        if name == "queue_step":
            runs += 1
            least_s = min(least_s, (last + p["interval"]) / CLOCK_HZ - sent_s)
            k = p["count"] - 1
            last += p["count"] * p["interval"] + p["add"] * (k * (k + 1) // 2)
    return runs, least_s


def test_a_longer_lead_holds_runs_back_longer_and_each_still_leaves_ahead() -> None:
    """A run that may still grow waits up to a quarter of the lead: a longer lead sends
    a cruise in fewer queue_steps, and every one leaves at least 3/4 lead - flush_s ahead
    of its first step (the host stall the MCU rides through)."""
    move = [Move((300.0, 0.0), 100.0, MoveKind.FEED, ToolMode.OFF, 0.0)]
    found = {}
    for lead_s in (0.2, 0.5):
        sink = Sink(Dictionary(FORMATS))
        run(move, CLOCK_HZ, lead_s, sink)
        runs, least_s = first_step_leads_s(sink, 0)
        assert least_s >= 0.75 * lead_s - 0.02 - 0.002, (lead_s, least_s)
        found[lead_s] = runs
    assert found[0.5] < 0.75 * found[0.2], found
