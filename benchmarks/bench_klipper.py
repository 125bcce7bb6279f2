"""The Klipper backend against Klipper's own host, on the stock firmware (the klipper-avr rig).

For each host (klippy at the firmware's commit, built by ``scripts/klippy-host``; motiond's
Klipper backend) a fresh rig, the host configured alike (:mod:`benchmarks.klipper_rig_hosts`),
then each job of :mod:`benchmarks.klipper_rig_jobs` ``--runs`` times. From the host's process,
the rig's serial log and its GPIO log (cycles at 20 MHz: the MCU's own time), per job:

* host CPU seconds per second of motion (the host's own process; motion from the first step
  edge to the last; the idle job: per second), the main thread's share of it (motiond's event
  loop, klippy's reactor), and how often the main thread and the others (chiefly each host's
  serial thread) were put on a CPU, per second;
* bytes, blocks and messages per second to the MCU, retransmitted blocks per second;
* cruise speed error in ppm (each cruise's steps over the cycles they took, against the
  commanded 100 mm/s), and step time error against the ideal trapezoid (p99 and max |µs|,
  one offset fitted per move), and p99 on the job's whole timeline (the moves back to back,
  one offset for the job: a drift from move to move counts), on the firmware's clock
  (simavr's lost timer overflows, 65,536 cycles each, taken out where the edges show one);
* wall time from sending the job to its last step, and whether every step count is exact;
* how long after the board's last step the host said the job was done (motiond: the ``ok`` to
  ``M400`` or the job's end, then Idle at the job's end on ``?``; klippy: its script's
  ``M400``): negative, it said so too early;
* with ``--clock-fit``, motiond's clock fit: each clock poll's prediction (motiond logs its
  polls at debug level, which costs it some CPU) against when the MCU read that clock;
* LAG records (the simulation fell behind wall-clock time: a loaded machine) in the window.

Run: ``python -m benchmarks klipper [--quick] [--json] [--runs N] [--motiond-tree DIR]
[--hosts klippy motiond] [--jobs raster circles long idle] [--logs DIR] [--lead-time-s S]
[--rig-pause-ms MS] [--feed job] [--clock-fit]``
(``--motiond-tree``: measure motiond from another checkout, e.g. a branch's worktree;
``--logs``: keep the logs there; ``--lead-time-s``: motiond's ``[backend] lead_time_s``,
default its own 0.3 s; ``--rig-pause-ms``: stop the simulator that long every 1.5 s, the lag
of a loaded host made repeatable).
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from benchmarks import klipper_rig_analysis as analysis
from benchmarks.common import REPO, BenchResult, add_run_options, execute
from benchmarks.klipper_options import HOSTS, JOBS, add_options, options_of
from benchmarks.klipper_rig_hosts import (
    KLIPPER_AVR,
    PAUSE_EVERY_S,
    STEPS_PER_MM,
    Klippy,
    Motiond,
    Rig,
    Threads,
    cpu_ns,
    klipper_rig,
    threads,
)
from benchmarks.klipper_rig_jobs import SPEED_MM_S, Job, jobs

if TYPE_CHECKING:
    from tests.support.klipper_rig import GpioLog

PINS = {"x": ("A0", "A1", True), "y": ("A3", "A4", False)}  # step, dir, dir inverted
SETTLE_S = 0.5
IDLE_SETTLE_S = 1.5  # the idle job's window starts at rest: motiond's loop monitor samples the
# loop every tick for a second after each command (QUIET_AFTER_S), a cost of the command


@dataclass
class Window:
    job: Job
    host: str
    start_ns: int
    end_ns: int
    cpu_s: float
    failure: str = ""
    threads: Threads = field(default_factory=Threads)


@dataclass
class Figures:
    cpu_per_s: float = float("nan")
    main_share: float = float("nan")  # of the CPU: the main thread's (event loop, reactor)
    main_runs_per_s: float = float("nan")  # the main thread put on a CPU, a second
    other_runs_per_s: float = float("nan")  # the other threads (the serial thread's)
    bytes_per_s: float = float("nan")
    messages_per_s: float = float("nan")
    blocks_per_s: float = float("nan")
    retransmits_per_s: float = float("nan")
    cruise_ppm: list[float] = field(default_factory=list)
    error_p99_us: float = float("nan")
    error_max_us: float = float("nan")
    error_job_p99_us: float = float("nan")
    wall_s: float = float("nan")
    done_after_ms: float = float("nan")  # the host said done this long after the last step
    motion_s: float = float("nan")
    exact: bool = True
    lag_records: int = 0
    lag_max_ms: float = 0.0
    by_message: dict[str, float] = field(default_factory=dict)  # messages/s by name
    bytes_per_block: float = float("nan")
    lone_blocks_per_s: float = float("nan")  # blocks of a single message
    steps_per_run: float = float("nan")  # the median queue_step's step count
    slips: int = 0
    slips_in_moves: int = 0
    failure: str = ""
    inexact: list[str] = field(default_factory=list)  # how each axis' count is off, if it is
    fit_errors_ms: list[float] = field(default_factory=list)  # motiond's clock fit, each poll


async def run_host(host: str, job_list: list[Job], runs: int, workdir: Path,
                   tree: Path, lead_time_s: float | None, rig_pause_ms: float,
                   feed: str = "stream", clock_fit: bool = False) -> tuple[Rig, list[Window]]:
    windows: list[Window] = []
    async with klipper_rig(workdir, host, rig_pause_ms) as rig:
        starter = Klippy.start(rig, workdir) if host == "klippy" else \
            Motiond.start(rig, workdir, tree, lead_time_s, "debug" if clock_fit else "warning")
        async with starter as driver:
            if feed == "job" and isinstance(driver, Motiond):
                await driver.run(["G1 X10 Y10 F6000"], (10.0, 10.0))
                await driver.warm_up()
            for _ in range(runs):
                for job in job_list:
                    setup = [f"G1 X{job.start[0]:.3f} Y{job.start[1]:.3f} F6000"]
                    cpu, started, failure = 0, time.monotonic_ns(), ""
                    before = Threads()
                    try:
                        await driver.run(setup, job.start)
                        await asyncio.sleep(IDLE_SETTLE_S if job.idle_s else SETTLE_S)
                        before = threads(driver.pid)
                        cpu, started = cpu_ns(driver.pid), time.monotonic_ns()
                        if job.idle_s:
                            await asyncio.sleep(job.idle_s)
                        else:
                            await feed_job(driver, job, host, feed)
                    except (RuntimeError, TimeoutError) as error:  # a lagging rig: say so
                        failure = str(error)[:300]
                    ended = time.monotonic_ns()
                    windows.append(Window(job, host, started, ended,
                                          (cpu_ns(driver.pid) - cpu) / 1e9, failure,
                                          threads(driver.pid) - before))
                    print(f"  {host:8} {job.name:11} {(ended - started) / 1e9:6.2f} s"
                          + (f" FAILED: {failure}" if failure else ""), file=sys.stderr)
                    if failure:
                        try:
                            await driver.recover(rig)
                        except (RuntimeError, TimeoutError, OSError) as error:
                            print(f"  {host:8} not recovered ({error}): its other runs are "
                                  "left out", file=sys.stderr)
                            return rig, windows
        return rig, windows


async def feed_job(driver: Klippy | Motiond, job: Job, host: str, feed: str) -> None:
    """klippy: one script; motiond: streamed by a sender, or played as a stored job."""
    if feed == "job" and isinstance(driver, Motiond):
        await driver.play(job.lines(host), job.end)
    else:
        await driver.run(job.lines(host), job.end)


def inexact_where(rises: np.ndarray, start: int, end: int) -> str:
    """Where a window's steps lie against its bounds (a count that is off near one points
    at the window, not the steps)."""
    if not rises.size:
        return "no step"
    return (f"first step {(rises[0] - start) / analysis.FREQ_HZ * 1e3:.1f} ms after the "
            f"window's start, last {(end - rises[-1]) / analysis.FREQ_HZ * 1e3:.1f} ms "
            "before its end")


def done_after_ms(gpio: GpioLog, sync: np.ndarray, start: int, end_ns: int,
                  wanted: dict[str, int]) -> float:
    """How long after the job's last step the host said it was done (the window's end):
    negative when that step came later. The job's last step is its own: on each step pin
    the ``wanted[pin]``-th rise from the window's start (its gross count), so the next job's
    first steps, which may come within a lead of the end, never count. NaN when fewer came."""
    last = None
    for step, count in wanted.items():
        if not count:
            continue
        rises = [c for c, v in gpio.edges.get(step, []) if v == 1 and c >= start]
        if len(rises) < count:
            return float("nan")
        last = rises[count - 1] if last is None else max(last, rises[count - 1])
    if last is None:
        return float("nan")
    return (end_ns - float(np.interp(last, sync[:, 0], sync[:, 1]))) / 1e6


def cycle_of(sync: np.ndarray, host_ns: int) -> int:
    """The rig's cycle at a CLOCK_MONOTONIC time (its 10 ms ``T`` records)."""
    return int(np.interp(host_ns, sync[:, 1], sync[:, 0]))


def analyse(rig: Rig, windows: list[Window], clock_log: Path | None = None) -> list[Figures]:
    from tests.support.klipper_rig import GpioLog  # noqa: PLC0415
    from tests.support.rigs import msgproto  # noqa: PLC0415

    gpio = GpioLog.read(rig.gpio_log)
    serial = analysis.read_serial_log(rig.serial_log, msgproto(),
                                      (KLIPPER_AVR / "klipper.dict").read_bytes())
    slips = analysis.clock_slips(serial.clocks)
    sync = np.array(gpio.sync, dtype=np.float64)
    fits = analysis.clock_fit_errors(clock_log.read_text().splitlines(), serial.clocks, sync) \
        if clock_log is not None and clock_log.exists() else []
    lags = [(int(w[0]), int(w[2])) for w in (line.split() for line in
                                             rig.gpio_log.read_text().splitlines())
            if len(w) == 3 and w[1] == "LAG"]
    out = []
    for window in windows:
        if window.failure:
            out.append(Figures(exact=False, failure=window.failure))
            continue
        start, end = cycle_of(sync, window.start_ns), cycle_of(sync, window.end_ns)
        fig = Figures()
        fig.slips = sum(start <= c < end for c, _ in slips)
        fig.fit_errors_ms = [e for sent_s, e in fits
                             if window.start_ns <= sent_s * 1e9 < window.end_ns]
        in_lag = [ns for c, ns in lags if start <= c < end]
        fig.lag_records, fig.lag_max_ms = len(in_lag), max(in_lag, default=0) / 1e6
        edges: dict[str, np.ndarray] = {}
        for axis, (step, dir_pin, inverted) in PINS.items():
            rises = np.array([c for c, v in gpio.edges.get(step, []) if v == 1 and
                              start <= c < end], dtype=np.float64)
            net = sum((-1 if inverted else 1) * (1 if gpio.level_at(dir_pin, int(c)) else -1)
                      for c in rises)
            gross_want, net_want = window.job.steps(0 if axis == "x" else 1)
            if (len(rises), net) != (gross_want, net_want):
                fig.exact = False
                where = inexact_where(rises, start, end)
                fig.inexact.append(f"{axis}: {len(rises)} steps, net {net:+d} (want "
                                   f"{gross_want}, {net_want:+d}), {where}")
            edges[axis] = rises
        all_edges = np.sort(np.concatenate(list(edges.values())))
        if window.job.idle_s:
            seconds = window.job.idle_s
        elif all_edges.size < 2:  # no motion at all: counted as inexact above
            out.append(fig)
            continue
        else:
            seconds = (all_edges[-1] - all_edges[0]) / analysis.FREQ_HZ
            fig.motion_s = seconds
            last_ns = float(np.interp(all_edges[-1], sync[:, 0], sync[:, 1]))
            fig.wall_s = (last_ns - window.start_ns) / 1e9
            fig.done_after_ms = done_after_ms(gpio, sync, start, window.end_ns, {
                step: window.job.steps(0 if axis == "x" else 1)[0]
                for axis, (step, _, _) in PINS.items()})
        wire = serial.window(start, end)
        fig.cpu_per_s = window.cpu_s / seconds
        used = window.threads
        fig.main_share = used.main_ns / 1e9 / window.cpu_s if window.cpu_s else float("nan")
        fig.main_runs_per_s = used.main_runs / seconds
        fig.other_runs_per_s = used.other_runs / seconds
        fig.bytes_per_s, fig.blocks_per_s = wire.bytes / seconds, wire.blocks / seconds
        fig.messages_per_s = wire.messages / seconds
        fig.retransmits_per_s = wire.retransmitted / seconds
        fig.by_message = {n: c / seconds for n, c in wire.by_name.items()}
        fig.bytes_per_block = wire.bytes / wire.blocks if wire.blocks else float("nan")
        fig.lone_blocks_per_s, fig.steps_per_run = wire.lone / seconds, wire.steps_per_run
        errors: list[np.ndarray] = []
        timeline: list[tuple[np.ndarray, np.ndarray]] = []  # (edges, ideal s) on the job's
        starts = window.job.move_starts_s()
        for axis, moves in window.job.moves.items():
            if not fig.exact:
                break
            counts = [round(m.distance_mm * STEPS_PER_MM) for m in moves]
            for k, (move, move_edges) in enumerate(zip(
                    moves, analysis.split_moves(edges[axis], counts), strict=True)):
                ideal = analysis.ideal_times(move, STEPS_PER_MM)
                timeline.append((move_edges, ideal + starts[axis][k]))
                move_edges, found = analysis.unslip(move_edges, ideal)
                fig.slips_in_moves += found
                errors.append(analysis.step_errors(move_edges, ideal))
                ppm = analysis.cruise_ppm(move_edges, move, STEPS_PER_MM)
                if ppm is not None:
                    fig.cruise_ppm.append(ppm)
        if errors:
            magnitudes = np.abs(np.concatenate(errors))
            fig.error_p99_us = analysis.percentile(magnitudes, 99)
            fig.error_max_us = float(magnitudes.max())
            job_edges, job_ideal = (np.concatenate(part) for part in zip(*timeline, strict=True))
            order = np.argsort(job_ideal, kind="stable")
            job_edges, _ = analysis.unslip(job_edges[order], job_ideal[order])
            fig.error_job_p99_us = analysis.percentile(
                np.abs(analysis.step_errors(job_edges, job_ideal[order])), 99)
        out.append(fig)
    return out


def finite(values: Sequence[float]) -> list[float]:
    return [v for v in values if np.isfinite(v)]


def median(runs: list[Figures], name: str) -> float:
    values = finite([getattr(f, name) for f in runs])
    return float(np.median(values)) if values else float("nan")


def span(values: Sequence[float], fmt: str) -> str:
    finite = [v for v in values if np.isfinite(v)]
    if not finite:
        return "-"
    low, high = min(finite), max(finite)
    return format(low, fmt) if format(low, fmt) == format(high, fmt) else \
        f"{format(low, fmt)}..{format(high, fmt)}"


def message_mix(runs: list[Figures]) -> str:
    """Where the bytes go: bytes a block, blocks of one message per second, the median
    queue_step's steps, and messages per second by name (medians of the runs)."""
    names = sorted({n for f in runs for n in f.by_message},
                   key=lambda n: -median_of([f.by_message.get(n, 0.0) for f in runs]))
    mix = ", ".join(f"{n} {median_of([f.by_message.get(n, 0.0) for f in runs]):.1f}"
                    for n in names)
    return (f"{median(runs, 'bytes_per_block'):.1f} bytes/block, "
            f"{median(runs, 'lone_blocks_per_s'):.1f} blocks/s of one message, "
            f"{median(runs, 'steps_per_run'):.0f} steps/queue_step; messages/s: {mix or '-'}")


def thread_mix(runs: list[Figures]) -> str:
    """The main thread's share of the CPU, and how often the threads run (medians)."""
    return (f"main thread {100 * median(runs, 'main_share'):.0f}% of the CPU, on a CPU "
            f"{median(runs, 'main_runs_per_s'):.0f} times a second; the other threads "
            f"{median(runs, 'other_runs_per_s'):.0f}")


def median_of(values: list[float]) -> float:
    return float(np.median(values)) if values else 0.0


def report(result: BenchResult, figures: dict[str, dict[str, list[Figures]]]) -> None:
    names = list(next(iter(figures.values())))
    columns = (("cpu_per_s", "CPU s/s", ".4f", "s/s"), ("bytes_per_s", "bytes/s", ",.0f", "B/s"),
               ("messages_per_s", "msgs/s", ",.0f", "1/s"),
               ("retransmits_per_s", "retx/s", ".2f", "1/s"),
               ("error_p99_us", "step p99 µs", ".1f", "µs"),
               ("error_max_us", "step max µs", ".1f", "µs"),
               ("error_job_p99_us", "job p99 µs", ",.0f", "µs"), ("wall_s", "wall s", ".2f", "s"),
               ("done_after_ms", "done after ms", ".1f", "ms"))
    print(f"{'job':11} {'host':8} " + " ".join(f"{c[1]:>16}" for c in columns)
          + f" {'cruise ppm':>16} exact  lag slips failed")
    for name in names:
        for host, by_job in figures.items():
            runs = by_job[name]
            cells = [span([getattr(f, c[0]) for f in runs], c[2]) for c in columns]
            ppm = [p for f in runs for p in f.cruise_ppm]
            lag = sum(f.lag_records for f in runs)
            failed = [f.failure for f in runs if f.failure]
            exact = all(f.exact for f in runs if not f.failure)
            inexact = ["; ".join(f.inexact) for f in runs if f.inexact]
            for how in inexact:
                print(f"{'':11} {'':8} not exact: {how}")
            print(f"{name:11} {host:8} " + " ".join(f"{c:>16}" for c in cells)
                  + f" {span(ppm, '+.0f'):>16} {exact!s:5} {lag:4} "
                  f"{sum(f.slips_in_moves for f in runs):5} {len(failed):6}")
            traffic = message_mix(runs)
            print(f"{'':11} {'':8} {traffic}")
            print(f"{'':11} {'':8} {thread_mix(runs)}")
            fit = np.abs([e for f in runs for e in f.fit_errors_ms])
            if fit.size:
                print(f"{'':11} {'':8} clock fit, each poll's prediction against the rig's "
                      f"clock: {fit.size} polls, |error| p50 {np.median(fit):.2f}, p90 "
                      f"{analysis.percentile(fit, 90):.2f}, max {fit.max():.2f} ms")
            per_run = "; per run: step p99 µs " + ", ".join(
                f"{f.error_p99_us:.0f}" for f in runs) + "; cruise ppm " + " | ".join(
                ", ".join(f"{p:+.0f}" for p in f.cruise_ppm) for f in runs)
            result.add(name, host, note=f"{len(runs)} runs, {len(failed)} failed; {lag} LAG "
                       "records" + "".join(f"; failed: {reason}" for reason in failed)
                       + "".join(f"; not exact: {how}" for how in inexact)
                       + (per_run if any(f.cruise_ppm for f in runs) else ""),
                       **{f"{c[0]}_{k}": (fn(finite([getattr(f, c[0]) for f in runs]),
                                             default=float("nan")), c[3])
                          for c in columns for k, fn in (("min", min), ("max", max))},
                       cruise_ppm_min=(min(ppm, default=float("nan")), "ppm"),
                       cruise_ppm_max=(max(ppm, default=float("nan")), "ppm"),
                       exact=(float(exact), "bool"), failed=(float(len(failed)), "runs"),
                       lag_records=(float(lag), "records"),
                       main_thread_share=(median(runs, "main_share"), "share"),
                       main_thread_runs_per_s=(median(runs, "main_runs_per_s"), "1/s"),
                       other_threads_runs_per_s=(median(runs, "other_runs_per_s"), "1/s"),
                       lag_max=(max((f.lag_max_ms for f in runs), default=0.0), "ms"),
                       fit_error_p50=(float(np.median(fit)) if fit.size else float("nan"), "ms"),
                       fit_error_max=(float(fit.max()) if fit.size else float("nan"), "ms"),
                       clock_slips=(float(sum(f.slips for f in runs)), "slips"),
                       slips_taken_out=(float(sum(f.slips_in_moves for f in runs)), "slips"))
        if len(figures) == 2:
            ratios = {c[0]: median(figures["motiond"][name], c[0])
                      / median(figures["klippy"][name], c[0])
                      for c in columns[:2] + columns[4:5] + columns[6:8]}
            ratios = {k: v for k, v in ratios.items() if np.isfinite(v)}
            print(f"{name:11} {'ratio':8} " + "  ".join(f"{k} {v:.2f}x" for k, v in
                                                        ratios.items()) + " (motiond / klippy)")
            result.add(name, "motiond / klippy", **{k: (v, "x") for k, v in ratios.items()})


async def measure(quick: bool, runs: int, tree: Path, hosts: Sequence[str],
                  logs: Path | None = None, lead_time_s: float | None = None,
                  rig_pause_ms: float = 0.0, job_names: Sequence[str] = JOBS,
                  feed: str = "stream",
                  clock_fit: bool = False) -> dict[str, dict[str, list[Figures]]]:
    job_list = [job for job in jobs(quick) if job.name.split()[0] in job_names]
    figures: dict[str, dict[str, list[Figures]]] = {}
    with tempfile.TemporaryDirectory(prefix="motiond-bench-klipper-") as name:
        for host in hosts:
            workdir = (logs or Path(name)) / host
            workdir.mkdir(parents=True, exist_ok=True)
            rig, windows = await run_host(host, job_list, runs, workdir, tree, lead_time_s,
                                          rig_pause_ms, feed, clock_fit)
            by_job: dict[str, list[Figures]] = {job.name: [] for job in job_list}
            clock_log = workdir / "motiond.err" if host == "motiond" and clock_fit else None
            for window, fig in zip(windows, analyse(rig, windows, clock_log), strict=True):
                by_job[window.job.name].append(fig)
            figures[host] = by_job
    return figures


def run(quick: bool, runs: int | None = None, motiond_tree: Path | None = None,
        hosts: Sequence[str] = HOSTS, logs: Path | None = None,
        lead_time_s: float | None = None, rig_pause_ms: float = 0.0,
        job_names: Sequence[str] = JOBS, feed: str = "stream",
        clock_fit: bool = False) -> BenchResult:
    result = BenchResult("klipper", quick)
    runs = runs or (1 if quick else 3)
    tree = (motiond_tree or REPO).resolve()
    print(f"stock Klipper firmware (klipper-avr rig), {runs} run(s) per job and host; "
          f"motiond from {tree}" + (f" (lead_time_s {lead_time_s})" if lead_time_s else "")
          + f"; commanded {SPEED_MM_S:.0f} mm/s"
          + ("; motiond plays each job stored" if feed == "job" else "")
          + (f"; the rig paused {rig_pause_ms:g} ms every {PAUSE_EVERY_S:g} s"
             if rig_pause_ms else ""))
    report(result, asyncio.run(measure(quick, runs, tree, hosts, logs, lead_time_s,
                                       rig_pause_ms, job_names, feed, clock_fit)))
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    add_run_options(parser)
    add_options(parser)
    options = parser.parse_args(argv)
    return execute([lambda: run(options.quick, **options_of(options))], options.json)


if __name__ == "__main__":
    sys.exit(main())
