"""A virtual Klipper MCU on a real pty: the one stand-in for hardware the tests allow.

It serves Klipper's documented protocol (docs/Protocol.md, docs/MCU_Commands.md): message
blocks with sequence numbers, acks and naks, ``identify`` with a zlib-compressed data
dictionary, a free-running clock (``CLOCK_FREQ`` ticks from its own start, optionally drifting),
config with a CRC, and a shared move queue. It executes ``queue_step`` as Klipper's
src/stepper.c does (step ``k`` at ``last + (k+1)·interval + add·k(k+1)/2``, direction from
``set_next_step_dir``) and records every step with its MCU clock, every PWM update, and how
full the move queue got and how early each move arrived. Every byte from the host is decoded
with Klipper's own host-side parser (``msgproto.py`` at the stock firmware's commit, from the
klipper-avr rig), the reference decoder. It offers only the commands the stock firmware has
(:mod:`tests.support.klipper_dictionary`); like the firmware, a shut-down MCU answers
``is_shutdown`` to everything but the few commands allowed then, ``clear_shutdown`` resumes it
with its configuration (steps and outputs dropped), ``reset`` restarts it, and an output with a
``max_duration`` left on longer than that without a new event shuts it down.

A microcontroller runs on its own core whatever the host does; this one is a thread of the
test process, so while it runs it asks for the CPU first: real-time priority for its thread
(when allowed, as in CI) and a 0.5 ms GIL switch interval, or a loaded machine would make it
read the host's messages late and shut down ("Stepper too far in past") where no MCU would.

With ``baud``, the host's bytes take their wire time: a block is acted on (and acknowledged) when
its last byte would have arrived at that rate after the bytes before it, as on a UART; without,
at once, as over USB.

Faults for tests: :meth:`mute` (stops answering), :meth:`restart` (clock, sequence and config
start over), ``drop_blocks``/``corrupt_blocks`` (the next N host blocks are lost or damaged),
:meth:`shutdown` (a firmware fault).
"""

from __future__ import annotations

import contextlib
import os
import pty
import select
import sys
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.support.klipper_dictionary import compressed, dictionary_data
from tests.support.rigs import msgproto as reference_msgproto

msgproto = reference_msgproto()
IN_SHUTDOWN = ("identify", "get_uptime", "get_clock", "get_config", "emergency_stop",
               "clear_shutdown", "reset")  # the stock commands with HF_IN_SHUTDOWN


@dataclass
class StepRecord:
    """One executed queue_step: its steps' clocks (after cancellation at a shutdown)."""

    clocks: np.ndarray
    direction: int
    received_clock: int


@dataclass
class Stepper:
    step_pin: str
    dir_pin: str
    last_clock: int = 0
    next_dir: int = 0
    runs: list[StepRecord] = field(default_factory=list)


@dataclass
class OutputPin:
    pin: str
    kind: str  # "pwm" or "digital"
    default: int
    events: list[tuple[int, int]] = field(default_factory=list)  # (clock, value)
    max_duration: int = 0  # ticks an output may stay off its default without a new event


class VirtualMcu:
    """See the module docstring. ``start()`` it, point the host at ``path``, ``stop()`` it."""

    def __init__(self, clock_hz: int = 72_000_000, id_offset: int = 0, move_count: int = 512,
                 drift_ppm: float = 0.0, baud: int | None = None) -> None:
        self.clock_hz = clock_hz
        self.baud = baud
        self._wire_free_s = 0.0  # when the bytes read so far have all come over the wire
        self.move_count = move_count
        self.data = dictionary_data(clock_hz, id_offset, move_count)
        self.blob = compressed(self.data)
        self.parser = msgproto.MessageParser()
        self.parser.process_identify(self.blob)
        self._formats = {fmt: fid for fmt, fid in self.data["responses"].items()}
        self.rate = clock_hz * (1.0 + drift_ppm * 1e-6)
        self.master, self._slave = pty.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self.lock = threading.RLock()
        self.muted = False
        self.hold_config: threading.Event | None = None  # a get_config reply waits for it
        self.holding_config = threading.Event()  # ...and this says one is waiting
        self.drop_blocks = 0
        self.lose_after_riding_poll_s = 0.0  # after the next get_clock that shares a block
        # with steps is answered, its clock falls this far behind (as a simulated board that
        # drops timer overflows does): the host's next reading is a poll period on
        self.corrupt_blocks = 0
        self.resets = 0  # ``reset`` commands obeyed
        self.naks_sent = 0
        self.blocks_received = 0
        self.block_messages: list[list[str]] = []  # each block's message names, in order
        self.commands: list[tuple[int, str, dict[str, Any]]] = []  # (clock, name, params)
        self.shutdowns: list[str] = []
        self.refused: list[str] = []  # commands the MCU could not carry out
        self.max_moves_in_use = 0
        self.min_lead_ticks = float("inf")  # earliest a move arrived before it was due
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="virtual-mcu", daemon=True)
        self._buffer = bytearray()
        self._power_on()

    # -- lifecycle and faults -----------------------------------------------------------------
    def start(self) -> VirtualMcu:
        self._switch_interval_s = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval_s, 0.0005))
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        sys.setswitchinterval(self._switch_interval_s)
        os.close(self.master)
        os.close(self._slave)

    def mute(self) -> None:
        with self.lock:
            self.muted = True

    def restart(self) -> None:
        """A reset: clock from zero, sequence from zero, unconfigured, outputs at rest."""
        with self.lock:
            self._cancel_future(self.clock())
            self._power_on()

    def _archive(self) -> None:
        """Objects go (a restart); what they did stays in the records."""
        for oid, stepper in self.steppers.items():
            self.old_runs.setdefault(oid, []).extend(stepper.runs)
        self.old_outputs.extend(self.outputs.values())
        self.steppers, self.outputs = {}, {}

    def output_events(self, pin: str) -> list[tuple[int, int]]:
        """Every value the pin was set to, with its clock, across reconfigurations."""
        with self.lock:
            outputs = self.old_outputs + list(self.outputs.values())
            return [e for out in outputs if out.pin == pin for e in out.events]

    def _power_on(self) -> None:
        self._t0 = time.monotonic()
        self.expected_seq = 0
        self.configured = False
        self.crc = 0
        self.oid_count = 0
        self.shutdown_reason: str | None = None
        self.old_runs: dict[int, list[StepRecord]] = getattr(self, "old_runs", {})
        self.old_outputs: list[OutputPin] = getattr(self, "old_outputs", [])
        if hasattr(self, "steppers"):
            self._archive()
        self.steppers: dict[int, Stepper] = {}
        self.outputs: dict[int, OutputPin] = {}
        self._queue_free_at: list[int] = []  # clock at which each queued move leaves the queue

    def clock(self) -> int:
        return int((time.monotonic() - self._t0) * self.rate)

    # -- results ------------------------------------------------------------------------------
    def step_clocks(self, oid: int) -> tuple[np.ndarray, np.ndarray]:
        """Every step the stepper made: MCU clocks and +1/-1 directions, in order."""
        with self.lock:
            current = self.steppers[oid].runs if oid in self.steppers else []
            runs = self.old_runs.get(oid, []) + list(current)
        if not runs:
            return np.empty(0, np.int64), np.empty(0, np.int64)
        clocks = np.concatenate([r.clocks for r in runs])
        dirs = np.concatenate([np.full(len(r.clocks), 1 if r.direction else -1) for r in runs])
        return clocks, dirs

    # -- the serial side ----------------------------------------------------------------------
    def _serve(self) -> None:
        with contextlib.suppress(OSError):  # not allowed: an ordinary thread, as before
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))  # this thread only
        while not self._stop.is_set():
            try:  # the pty may be closed and replaced meanwhile (tests.support.hostile_mcu)
                ready, _, _ = select.select([self.master], [], [], 0.02)
            except (OSError, ValueError):
                ready = []
                time.sleep(0.02)
            if not ready:
                with self.lock:
                    self._check_watchdogs()
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                continue
            with self.lock:
                if not self.muted:
                    self._receive(data)
                self._check_watchdogs()

    def _receive(self, data: bytes) -> None:
        self._buffer += data
        self._wire_free_s = max(self._wire_free_s, time.monotonic())
        while self._buffer:
            if self._buffer[0] == msgproto.MESSAGE_SYNC:
                del self._buffer[0]
                continue
            size = self.parser.check_packet(self._buffer)
            if size == 0:
                return
            if size < 0:  # damaged: drop to the next sync byte and ask again
                del self._buffer[:-size]
                self._send_block(b"")
                self.naks_sent += 1
                continue
            block = bytes(self._buffer[:size])
            del self._buffer[:size]
            if self.baud is not None:  # its last byte comes after the bytes before it
                self._wire_free_s += size * 10 / self.baud
                time.sleep(max(0.0, self._wire_free_s - time.monotonic()))
            self._block(block)

    def _block(self, block: bytes) -> None:
        if self.drop_blocks:
            self.drop_blocks -= 1
            return
        if self.corrupt_blocks:
            self.corrupt_blocks -= 1
            self._send_block(b"")  # the MCU saw a bad CRC: nak
            self.naks_sent += 1
            return
        seq = block[msgproto.MESSAGE_POS_SEQ] & msgproto.MESSAGE_SEQ_MASK
        if seq != self.expected_seq & msgproto.MESSAGE_SEQ_MASK:
            self._send_block(b"")
            self.naks_sent += 1
            return
        self.expected_seq += 1
        self.blocks_received += 1
        pos, resets = msgproto.MESSAGE_HEADER_SIZE, self.resets
        messages: list[tuple[str, dict[str, Any]]] = []
        while pos < len(block) - msgproto.MESSAGE_TRAILER_SIZE:
            fmt = self.parser.messages_by_id[block[pos]]
            params, pos = fmt.parse(block, pos)
            messages.append((fmt.name, params))
        # recorded whole before the first response leaves (a test reading it on a reply sees
        # the block it came in)
        self.block_messages.append([name for name, _ in messages])
        for name, params in messages:
            self._command(name, params)
        names = self.block_messages[-1]
        if self.lose_after_riding_poll_s and "get_clock" in names and "queue_step" in names:
            self._t0 += self.lose_after_riding_poll_s
            self.lose_after_riding_poll_s = 0.0
        if self.resets == resets:  # acked after its responses, as src/command.c does (a
            self._send_block(b"")  # reset reboots first)

    def _send_block(self, payload: bytes) -> None:
        out = bytearray([len(payload) + 5, 0x10 | (self.expected_seq & 0xF)]) + payload
        out += bytes(msgproto.crc16_ccitt(out)) + bytes([msgproto.MESSAGE_SYNC])
        os.write(self.master, bytes(out))

    def respond(self, text: str, *values: Any) -> None:
        fmt = self.parser.lookup_command(text)
        self._send_block(bytes(fmt.encode(list(values))))

    # -- commands -----------------------------------------------------------------------------
    def _command(self, name: str, params: dict[str, Any]) -> None:
        now = self.clock()
        self.commands.append((now, name, params))
        handler = getattr(self, f"_cmd_{name}", None)
        if handler is None:
            raise AssertionError(f"virtual MCU: unexpected command {name}")
        if self.shutdown_reason is not None and name not in IN_SHUTDOWN:
            self.respond("is_shutdown static_string_id=%hu", self.shutdown_reason)
            return
        try:
            handler(now, **params)
        except (KeyError, AssertionError) as exc:  # what the firmware refuses: an unknown oid
            self.refused.append(f"{name} {params}: {exc!r}")
            self.shutdown("Invalid oid type", now)

    def shutdown(self, reason: str, now: int | None = None) -> None:
        if self.shutdown_reason is not None:
            return
        now = self.clock() if now is None else now
        self.shutdown_reason = reason
        self.shutdowns.append(reason)
        self._cancel_future(now)
        self.respond("shutdown clock=%u static_string_id=%hu", now & 0xFFFFFFFF, reason)

    def _cancel_future(self, now: int) -> None:
        """Steps and output changes not yet made never happen; outputs go to their defaults."""
        runs = [r for s in self.steppers.values() for r in s.runs]
        for run in runs + [r for old in self.old_runs.values() for r in old]:
            run.clocks = run.clocks[run.clocks <= now]
        for out in self.outputs.values():
            out.events = [e for e in out.events if e[0] <= now] + [(now, out.default)]
        self._queue_free_at.clear()

    def _cmd_identify(self, now: int, offset: int, count: int) -> None:
        self.respond("identify_response offset=%u data=%.*s", offset,
                     self.blob[offset:offset + count])

    def _cmd_get_uptime(self, now: int) -> None:
        self.respond("uptime high=%u clock=%u", now >> 32, now & 0xFFFFFFFF)

    def _cmd_get_clock(self, now: int) -> None:
        self.respond("clock clock=%u", now & 0xFFFFFFFF)

    def _cmd_get_config(self, now: int) -> None:
        state = (int(self.configured), self.crc, int(self.shutdown_reason is not None))
        hold = self.hold_config
        if hold is not None:  # the reply is on the wire while the host goes on: a race, held
            self.hold_config = None
            self.holding_config.set()
            hold.wait(5.0)
        self.respond("config is_config=%c crc=%u is_shutdown=%c move_count=%hu", *state,
                     self.move_count)

    def _cmd_allocate_oids(self, now: int, count: int) -> None:
        assert not self.configured and self.oid_count == 0
        self.oid_count = count

    def _cmd_config_stepper(self, now: int, oid: int, step_pin: str, dir_pin: str,
                            invert_step: int, step_pulse_ticks: int) -> None:
        assert not self.configured and oid < self.oid_count
        self.steppers[oid] = Stepper(step_pin, dir_pin)

    def _cmd_config_digital_out(self, now: int, oid: int, pin: str, value: int,
                                default_value: int, max_duration: int) -> None:
        assert not self.configured and oid < self.oid_count
        self.outputs[oid] = OutputPin(pin, "digital", default_value, [(now, value)],
                                      max_duration)

    def _cmd_config_pwm_out(self, now: int, oid: int, pin: str, cycle_ticks: int, value: int,
                            default_value: int, max_duration: int) -> None:
        assert not self.configured and oid < self.oid_count and cycle_ticks > 0
        self.outputs[oid] = OutputPin(pin, "pwm", default_value, [(now, value)], max_duration)

    def _cmd_finalize_config(self, now: int, crc: int) -> None:
        self.configured, self.crc = True, crc

    def _cmd_emergency_stop(self, now: int) -> None:
        self.shutdown("Command request", now)

    def _cmd_clear_shutdown(self, now: int) -> None:
        if self.shutdown_reason is None:
            self.shutdown("Shutdown cleared when not shutdown", now)
            return
        self.shutdown_reason = None
        for stepper in self.steppers.values():
            stepper.last_clock = 0

    def _cmd_reset(self, now: int) -> None:
        """The firmware's watchdog reboot: a fresh MCU that says ``starting``."""
        self.resets += 1
        self._cancel_future(now)
        self._power_on()
        self.respond("starting")

    def _check_watchdogs(self) -> None:
        """An output left off its default past its ``max_duration`` (no new event queued):
        the firmware shuts down (src/gpiocmds.c, "Missed scheduling of next ... event")."""
        if self.shutdown_reason is not None or not self.configured:
            return
        now = self.clock()
        for out in self.outputs.values():
            if not out.max_duration or not out.events:
                continue
            clock, value = out.events[-1]
            if value != out.default and now > clock + out.max_duration:
                kind = "hard pwm" if out.kind == "pwm" else "digital out"
                self.shutdown(f"Missed scheduling of next {kind} event", now)
                return

    def _use_queue(self, now: int, free_at: int) -> None:
        self._queue_free_at = [c for c in self._queue_free_at if c > now] + [free_at]
        self.max_moves_in_use = max(self.max_moves_in_use, len(self._queue_free_at))
        if len(self._queue_free_at) > self.move_count:
            self.shutdown("Move queue overflow")

    def _cmd_queue_step(self, now: int, oid: int, interval: int, count: int, add: int) -> None:
        stepper = self.steppers[oid]
        k = np.arange(count, dtype=np.int64)
        clocks = stepper.last_clock + (k + 1) * interval + add * (k * (k + 1) // 2)
        self.min_lead_ticks = min(self.min_lead_ticks, int(clocks[0]) - now)
        if clocks[0] < now:
            self.shutdown("Stepper too far in past")
            return
        free_at = stepper.runs[-1].clocks[-1] if stepper.runs and len(stepper.runs[-1].clocks) \
            else now
        stepper.runs.append(StepRecord(clocks, stepper.next_dir, now))
        stepper.last_clock = int(clocks[-1])
        self._use_queue(now, max(int(free_at), now))

    def _cmd_set_next_step_dir(self, now: int, oid: int, dir: int) -> None:  # noqa: A002
        self.steppers[oid].next_dir = dir

    def _cmd_reset_step_clock(self, now: int, oid: int, clock: int) -> None:
        stepper = self.steppers[oid]
        if stepper.runs and len(stepper.runs[-1].clocks) and stepper.runs[-1].clocks[-1] > now:
            self.shutdown("Can't reset time when stepper active")
            return
        stepper.last_clock = self._extend(now, clock)

    def _extend(self, now: int, clock32: int) -> int:
        delta = (clock32 - now) & 0xFFFFFFFF
        return now + (delta - (1 << 32) if delta & 0x80000000 else delta)

    def _cmd_stepper_get_position(self, now: int, oid: int) -> None:
        """Steps made since this stepper was configured, +1 for each with dir 1."""
        pos = sum(int(np.sum(r.clocks <= now)) * (1 if r.direction else -1)
                  for r in self.steppers[oid].runs)
        self.respond("stepper_position oid=%c pos=%i", oid, pos)

    def _queue_output(self, now: int, oid: int, clock32: int, value: int) -> None:
        out = self.outputs[oid]
        clock = self._extend(now, clock32)
        if clock < now:
            self.shutdown("Scheduled output in the past")
            return
        out.events.append((clock, value))
        self._use_queue(now, clock)

    def _cmd_queue_pwm_out(self, now: int, oid: int, clock: int, value: int) -> None:
        self._queue_output(now, oid, clock, value)

    def _cmd_queue_digital_out(self, now: int, oid: int, clock: int, on_ticks: int) -> None:
        self._queue_output(now, oid, clock, on_ticks)

    def _cmd_update_digital_out(self, now: int, oid: int, value: int) -> None:
        self.outputs[oid].events.append((now, value))
