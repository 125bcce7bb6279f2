"""Motion time is MCU time: the steps' intervals come from the planned motion at the MCU's
nominal CLOCK_FREQ, never from the host's estimate of the MCU's clock (pure, virtual time).

The real planner, step generator and Klipper backend run on a virtual clock; the MCU side is
the clock fit (set as a running fit would be) and a sink that decodes every message sent.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from benchmarks.bench_klipper_host import Listener, OfflineBackend, dictionary
from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import PAYLOAD_MAX
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.printclock import PrintClock
from server.config_loader import build_config
from server.machine.parts import planner_settings
from server.motion.moves import Move, MoveKind, ToolMode
from server.motion.planner import Planner
from server.motion.stepgen import StepGenerator

CLOCK_HZ = 16_000_000


class Sink:
    def __init__(self, dictionary: Dictionary) -> None:
        self.dictionary, self.messages = dictionary, []  # type: list[tuple[str, Any]]

        self.now_s, self.sent_s = 0.0, []  # type: float, list[float]
        self.bursts: list[list[int]] = []  # the size of each message of each send

    def send(self, *messages: bytes) -> None:
        self.bursts.append([len(m) for m in messages])
        for message in messages:
            decoded = self.dictionary.decode(message)
            self.messages.extend(decoded)
            self.sent_s += [self.now_s] * len(decoded)

    def sample(self) -> None:
        """The backend's tick reads the device here: there is none."""


class FittedMcu:
    """What the backend reads of an MCU: its dictionary, the clock fit, its move queue."""

    def __init__(self, fitted_hz: float) -> None:
        self.dictionary = dictionary(CLOCK_HZ)
        self.clock = ClockSync(CLOCK_HZ)
        self.clock.reset(0.0, 0)
        self.clock.freq_hz = fitted_hz  # what a fit of an MCU this far off the host says
        self.move_count = 1 << 30
        self.link = Sink(self.dictionary)


def run(moves: list[Move], fitted_hz: float, lead_time_s: float = 0.2,
        sink: Sink | None = None, clock: ClockSync | None = None,
        sparse: bool = False) -> list[tuple[str, Any]]:
    """Every message the backend sends for ``moves`` with the fit at ``fitted_hz``
    (``sink``: where they go, with the virtual time each was sent at), ticked every
    millisecond, or when the backend asks (``sparse``: as the server ticks)."""
    axes = {a: {"steps_per_mm": 80, "max_rate_mm_s": 300, "accel_mm_s2": 3000, "max_mm": 400}
            for a in "xy"}
    pins = {"x": {"step_pin": "PB13", "dir_pin": "PB12"},
            "y": {"step_pin": "PB10", "dir_pin": "PB2"}}
    core = build_config({"axes": axes, "backend": {
        "kind": "klipper", "serial": "/dev/null", "axes": pins,
        "lead_time_s": lead_time_s}}).core
    backend = OfflineBackend(core)
    mcu = FittedMcu(fitted_hz)
    if clock is not None:
        mcu.clock = clock
    if sink is not None:
        mcu.link = sink
    backend.mcu, backend.ready = mcu, True  # type: ignore[assignment]
    for oid, axis in enumerate(backend.axes):  # what configuring the MCU sets
        axis.configure(oid, mcu.dictionary, backend.cfg.max_error_s * CLOCK_HZ)
    planner = Planner(planner_settings(core), (0.0, 0.0))
    stepgen = StepGenerator(planner, backend, (80.0, 80.0), Listener())
    for move in moves:
        planner.append(move)
    now_s = 0.0
    stepgen.tick(now_s)
    stepgen.request_start()
    while not stepgen.idle or now_s < 0.5:
        now_s = stepgen.next_tick_s(now_s, now_s) if sparse else now_s + 0.001
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


def steer_through(sched: PrintClock, fitted_clock: Callable[[float], float], seconds: float
                  ) -> tuple[list[float], list[float]]:
    """Flushes every 20 ms for ``seconds`` against a fit that puts print time ``t`` at
    ``fitted_clock(t)``; the drift and the schedule's rate after each. Nothing already
    scheduled ever moves, and the schedule never goes back."""
    previous, drifts, rates = 0.0, [], []
    for k in range(1, round(seconds / 0.02) + 1):
        t = 0.02 * k
        before = float(sched.clock(t))
        sched.steer(t, fitted_clock(t))
        assert float(sched.clock(t)) == before, "steering changes nothing already scheduled"
        assert before > previous
        previous = before
        drifts.append(sched.drift_s(t, fitted_clock(t)))
        rates.append(sched.hz / CLOCK_HZ - 1.0)
    return drifts, rates


def new_schedule() -> PrintClock:
    sched = PrintClock(CLOCK_HZ, 0.01, 0.05)
    sched.anchor(0.0, 0.0)
    return sched


def test_a_board_that_falls_behind_and_catches_up_moves_no_step_interval() -> None:
    """A simulated board on a loaded host: 40 ms behind over 2 s, then caught up in 0.5 s (the
    fit's rate bent by -20,000 and +80,000 ppm meanwhile). The lead only grew: the schedule
    keeps its nominal rate throughout."""
    def lagging(t: float) -> float:
        behind_s = float(np.interp(t, [10.0, 12.0, 12.5], [0.0, 0.04, 0.0]))
        return CLOCK_HZ * (t - behind_s)

    drifts, rates = steer_through(new_schedule(), lagging, 30.0)
    assert min(drifts) < -0.039 and max(drifts) < 1e-9
    assert set(rates) == {0.0}


def test_a_board_ahead_beyond_10_ms_is_caught_up_at_most_500_ppm_fast_never_at_the_fit() -> None:
    """A board 300 ppm fast (its fit too): nominal until the lead has shrunk 10 ms, then the
    steps run at most 500 ppm fast (not the fit's rate), and the lead never shrinks much more;
    a fit 5,000 ppm fast is never followed beyond 500 ppm either."""
    drifts, rates = steer_through(new_schedule(), lambda t: CLOCK_HZ * 1.0003 * t, 300.0)
    first = next(k for k, rate in enumerate(rates) if rate)
    assert 0.0098 < drifts[first] < 0.0101 and set(rates[:first]) == {0.0}
    assert max(drifts) < 0.02 and min(rates[first:]) > 0.0 and max(rates) <= 500e-6
    _, rates = steer_through(new_schedule(), lambda t: CLOCK_HZ * 1.005 * t, 60.0)
    assert abs(max(rates) - 500e-6) < 1e-12


def test_a_board_behind_beyond_50_ms_is_slowed_down_by_at_most_500_ppm() -> None:
    """A board 300 ppm slow: the lead may grow 50 ms before the steps slow down, by at most
    500 ppm; it then stays within reach of the bound."""
    drifts, rates = steer_through(new_schedule(), lambda t: CLOCK_HZ * 0.9997 * t, 400.0)
    first = next(k for k, rate in enumerate(rates) if rate)
    assert -0.0501 < drifts[first] < -0.0499 and set(rates[:first]) == {0.0}
    assert min(drifts) > -0.06 and max(rates[first:]) < 0.0 and min(rates) >= -500e-6


def test_a_fit_that_bends_by_thousands_of_ppm_mid_move_changes_no_step_interval() -> None:
    """The backend through a fit that says the board fell 30 ms behind mid-job and caught up
    (its rate 3,000 ppm off): every queue_step is the one a steady fit gives."""
    class Bent(ClockSync):
        def clock_at(self, host_s: float) -> float:
            behind_s = float(np.interp(host_s, [0.3, 0.8, 1.0], [0.0, 0.03, 0.0]))
            self.freq_hz = CLOCK_HZ * (1.003 if 0.3 < host_s < 1.0 else 1.0)
            return CLOCK_HZ * (host_s - behind_s)

    nominal = steps(run(JOB, CLOCK_HZ))
    assert steps(run(JOB, CLOCK_HZ, clock=Bent(CLOCK_HZ))) == nominal


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
    """A run that may still grow waits up to all of the lead but 150 ms (at least a quarter
    of it): a longer lead sends a cruise in fewer queue_steps, and every one leaves at least
    the lead less that hold-back less flush_s ahead of its first step (the host stall the MCU
    rides through: 130 ms from a 0.2 s lead on)."""
    move = [Move((300.0, 0.0), 100.0, MoveKind.FEED, ToolMode.OFF, 0.0)]
    found = {}
    for lead_s in (0.1, 0.2, 0.5):
        sink = Sink(dictionary(CLOCK_HZ))
        run(move, CLOCK_HZ, lead_s, sink)
        runs, least_s = first_step_leads_s(sink, 0)
        ride_through_s = min(0.75 * lead_s, 0.15) - 0.02
        assert least_s >= ride_through_s - 0.002, (lead_s, least_s)
        found[lead_s] = runs
    assert found[0.5] < 0.5 * found[0.2] and found[0.2] < 0.75 * found[0.1], found


def last_block_bytes(sizes: list[int]) -> int:
    """How full the last block of messages of these sizes is, packed in order."""
    fill = 0
    for size in sizes:
        fill = size if fill + size > PAYLOAD_MAX else fill + size
    return fill


def first_steps(messages: list[tuple[str, Any]]) -> dict[int, int]:
    """Each ``queue_step``'s index among ``messages``: the MCU clock of its first step."""
    firsts, last = {}, {0: 0, 1: 0}
    for index, (name, p) in enumerate(messages):
        if name == "reset_step_clock":
            last[p["oid"]] = p["clock"]
        if name == "queue_step":
            firsts[index] = last[p["oid"]] + p["interval"]
            k = p["count"] - 1
            last[p["oid"]] += p["count"] * p["interval"] + p["add"] * (k * (k + 1) // 2)
    return firsts


def test_a_sample_sends_all_that_turns_before_another_flush_could_come() -> None:
    """Ticked as the server ticks this backend: a sample sends every run whose first step
    is due within 3/4 lead and a flush (170 ms), whichever axis: none of them is left for a
    later sample, so runs that turn close together take one wake-up, not one each."""
    sink = Sink(dictionary(CLOCK_HZ))
    run(JOB, CLOCK_HZ, 0.2, sink, sparse=True)
    sent_at = sorted(set(sink.sent_s))
    firsts = first_steps(sink.messages)
    assert len(firsts) > 100
    for index, first in firsts.items():
        before = [t for t in sent_at if t < sink.sent_s[index]]
        if before:  # not due at the last sample before it
            assert first / CLOCK_HZ > before[-1] + 0.15 + 0.02 - 1e-6, (index, before[-1])


def test_a_part_filled_block_leaves_only_once_something_in_it_is_due() -> None:
    """Messages not yet urgent wait to share a block: every burst whose last block is not
    full (no room for a queue_step of 13 bytes more) has a queue_step due within 3/4 lead
    and a flush (170 ms) of leaving (a sample's horizon), and the job's messages share
    blocks (ticked as the server ticks this backend: when it asks)."""
    sink = Sink(dictionary(CLOCK_HZ))
    run(JOB, CLOCK_HZ, 0.2, sink, sparse=True)
    firsts = first_steps(sink.messages)
    index = 0
    for sizes in sink.bursts:
        leads = [firsts[i] / CLOCK_HZ - sink.sent_s[i] for i in range(index, index + len(sizes))
                 if i in firsts]
        full = last_block_bytes(sizes) > PAYLOAD_MAX - 13
        assert full or min(leads) <= 0.15 + 0.02 + 0.001, (sizes, leads)
        index += len(sizes)
    assert len(sink.messages) > 2.5 * len(sink.bursts)
