"""What the klipper-avr rig's logs say a host did (pure: no processes, no I/O but reading logs).

* :func:`read_serial_log`: the blocks the host sent (``MCU_SERIAL_LOG``'s ``R`` bytes), each with
  its cycle, size, sequence number and decoded messages, retransmissions (a block whose sequence
  number is not the next one), and the firmware's clock as its responses report it (``W``);
* :func:`clock_slips`: where simavr lost a timer-1 overflow (Klipper's clock falls 65,536 ticks
  behind the cycle count; the rig's README), as the firmware's clock responses show (counted),
  and :func:`unslip`: the same from a move's edges, exactly where it happened (taken out);
* :func:`ideal_times`: the ideal time of every step of a straight move along one axis (the
  trapezoid both hosts plan: accelerate, cruise, decelerate, from and to rest or a corner's
  junction speed; a step when the position crosses a half step, as both do);
* :func:`step_errors` and :func:`cruise_ppm`: edges against those ideal times (one offset fitted
  per move: when a move starts is free, its rate and shape are not) and the cruise speed.

Cycles count at 20 MHz (the firmware's ``CLOCK_FREQ``): the MCU's own time.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

import numpy as np
import numpy.typing as npt

FREQ_HZ = 20_000_000
SLIP_TICKS = 65_536
SYNC = 0x7E
FloatArray = npt.NDArray[np.float64]
CLOCK_RESPONSES = ("clock", "uptime", "stats")


@dataclass(slots=True)
class Block:
    """One block on the wire: the cycle its last byte passed, its bytes, sequence number and
    the names of its messages (an empty block is an ack or nak), and the step count of each
    ``queue_step`` in it."""

    cycle: int
    size: int
    seq: int
    messages: list[str]
    runs: list[int] = field(default_factory=list)


@dataclass(slots=True)
class SerialLog:
    sent: list[Block] = field(default_factory=list)  # host -> MCU (R)
    received: list[Block] = field(default_factory=list)  # MCU -> host (W)
    clocks: list[tuple[int, int]] = field(default_factory=list)  # (cycle, MCU clock) from W

    def window(self, start: int, end: int) -> SerialFigures:
        blocks = [b for b in self.sent if start <= b.cycle < end]
        retransmitted, fresh = 0, None  # fresh: the sequence number of the next new block
        for block in self.sent:
            if block.cycle >= end:
                break
            if not block.messages:
                continue
            if fresh is None or block.seq == fresh:
                fresh = (block.seq + 1) & 0x0F
            elif start <= block.cycle:
                retransmitted += 1  # an earlier sequence number again: sent anew
        by_name: dict[str, int] = {}
        for block in blocks:
            for name in block.messages or ["(ack)"]:
                by_name[name] = by_name.get(name, 0) + 1
        runs = [count for block in blocks for count in block.runs]
        return SerialFigures(bytes=sum(b.size for b in blocks), blocks=len(blocks),
                             messages=sum(len(b.messages) for b in blocks),
                             retransmitted=retransmitted, by_name=by_name,
                             lone=sum(len(b.messages) == 1 for b in blocks),
                             steps_per_run=float(np.median(runs)) if runs else math.nan)


@dataclass(frozen=True, slots=True)
class SerialFigures:
    bytes: int
    blocks: int
    messages: int
    retransmitted: int
    by_name: dict[str, int] = field(default_factory=dict)  # messages by name ("(ack)": empty)
    lone: int = 0  # blocks carrying a single message (5 bytes of framing for it alone)
    steps_per_run: float = math.nan  # the median queue_step's count


def crc16(data: bytes) -> bytes:
    """The link's CRC (CRC-16-CCITT as Klipper computes it), high byte first."""
    crc = 0xFFFF
    for byte in data:
        byte ^= crc & 0xFF
        byte ^= (byte << 4) & 0xFF
        crc = ((byte << 8) | (crc >> 8)) ^ (byte >> 4) ^ (byte << 3)
        crc &= 0xFFFF
    return bytes([crc >> 8, crc & 0xFF])


def encode_block(seq: int, payload: bytes) -> bytes:
    head = bytes([len(payload) + 5, 0x10 | (seq & 0x0F)]) + payload
    return head + crc16(head) + bytes([SYNC])


def split_blocks(data: bytes) -> list[tuple[int, bytes]]:
    """(end offset, block) for each well-formed block (length, sync byte and CRC) of a byte
    stream; anything else (a lone sync byte, damage) is skipped a byte at a time."""
    out: list[tuple[int, bytes]] = []
    pos = 0
    while pos < len(data):
        size = data[pos]
        block = data[pos:pos + size]
        if 5 <= size <= 64 and len(block) == size and block[-1] == SYNC \
                and crc16(block[:-3]) == block[-3:-1]:
            out.append((pos + size, block))
            pos += size
        else:
            pos += 1
    return out


def message_names(parser: object, block: bytes) -> list[tuple[str, dict[str, object]]]:
    """The messages of a block, decoded with Klipper's own ``msgproto`` parser."""
    out: list[tuple[str, dict[str, object]]] = []
    pos = 2
    while pos < len(block) - 3:
        msgid, _ = parser.msgid_parser.parse(block, pos)  # type: ignore[attr-defined]
        message = parser.messages_by_id.get(msgid, parser.unknown)  # type: ignore[attr-defined]
        params, pos = message.parse(block, pos)
        out.append((message.name, params))
    return out


def read_serial_log(path: Path, msgproto: ModuleType, dictionary: bytes) -> SerialLog:
    parser = msgproto.MessageParser()
    parser.process_identify(dictionary, decompress=False)
    streams: dict[str, tuple[bytearray, list[int]]] = {"R": (bytearray(), []),
                                                      "W": (bytearray(), [])}
    for line in path.read_text().splitlines():
        words = line.split()
        if len(words) == 3 and words[1] in streams and words[0].isdigit():
            data, cycles = streams[words[1]]
            chunk = bytes.fromhex(words[2])
            data += chunk
            cycles.extend([int(words[0])] * len(chunk))
    log = SerialLog()
    for direction, target in (("R", log.sent), ("W", log.received)):
        data, cycles = streams[direction]
        for end, block in split_blocks(bytes(data)):
            try:
                decoded = message_names(parser, block) if len(block) > 5 else []
            except Exception:  # noqa: BLE001 - damaged on the wire: counted, not decoded
                decoded = [("?", {})]
            cycle = cycles[end - 1]
            target.append(Block(cycle, len(block), block[1] & 0x0F, [n for n, _ in decoded],
                                [int(p["count"]) for n, p in decoded  # type: ignore
                                 if n == "queue_step"]))
            if direction == "W":
                log.clocks += [(cycle, int(p["clock"])) for n, p in decoded  # type: ignore
                               if n in CLOCK_RESPONSES and "clock" in p]
    return log


def clock_slips(clocks: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """(cycle, ticks behind) from each lost timer-1 overflow on: the MCU's clock as its
    responses report it, against the cycle count (a response leaves a little after its clock
    was read, far less than 65,536 ticks)."""
    out: list[tuple[int, int]] = []
    base: int | None = None
    behind = 0
    for cycle, clock in clocks:
        lag = (cycle - clock) % (1 << 32)
        if base is None:
            base = lag
        slips = round((lag - base) / SLIP_TICKS)
        if slips * SLIP_TICKS > behind:
            behind = slips * SLIP_TICKS
            out.append((cycle, behind))
    return out


CLOCK_SAMPLE = re.compile(r"clock (\S+) (\S+) (\d+) fit (\S+)$")
"""motiond's debug line for each clock poll: sent and received (host s), the MCU clock (64
bits), and the host time at which its clock fit put that clock before taking the poll."""


def clock_fit_errors(log_lines: Iterable[str], clocks: Sequence[tuple[int, int]],
                     sync: FloatArray) -> list[tuple[float, float]]:
    """(sent s, ms) for each of motiond's clock polls: how far its fit's prediction of the
    clock it read lay from when the MCU really read it. The truth is the rig's: the response
    carrying that clock left at a known cycle, the clock was read a few hundred µs before (its
    lag behind the cycle count, less whole lost overflows); ``sync`` maps cycles to host ns."""
    read_at = {clock: cycle - ((cycle - clock) % (1 << 32)) % SLIP_TICKS
               for cycle, clock in clocks}
    out = []
    for line in log_lines:
        found = CLOCK_SAMPLE.search(line)
        if found is None:
            continue
        cycle = read_at.get(int(found[3]) & 0xFFFFFFFF)
        if cycle is None:
            continue
        truth_s = float(np.interp(cycle, sync[:, 0], sync[:, 1])) / 1e9
        out.append((float(found[1]), (float(found[4]) - truth_s) * 1e3))
    return out


# -- the ideal profile -----------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Trapezoid:
    """A straight move along one axis: distance, commanded speed, acceleration (mm, mm/s,
    mm/s²) and the speeds it starts and ends at (0: at rest; a corner's junction speed)."""

    distance_mm: float
    speed_mm_s: float
    accel_mm_s2: float
    start_mm_s: float = 0.0
    end_mm_s: float = 0.0

    @property
    def peak_mm_s(self) -> float:
        v0, v1, a = self.start_mm_s, self.end_mm_s, self.accel_mm_s2
        return min(self.speed_mm_s, math.sqrt(a * self.distance_mm + (v0 * v0 + v1 * v1) / 2))

    @property
    def accel_mm(self) -> float:
        return (self.peak_mm_s ** 2 - self.start_mm_s ** 2) / (2 * self.accel_mm_s2)

    @property
    def decel_mm(self) -> float:
        return (self.peak_mm_s ** 2 - self.end_mm_s ** 2) / (2 * self.accel_mm_s2)

    @property
    def duration_s(self) -> float:
        a, peak = self.accel_mm_s2, self.peak_mm_s
        cruise_mm = self.distance_mm - self.accel_mm - self.decel_mm
        return (peak - self.start_mm_s) / a + cruise_mm / peak + (peak - self.end_mm_s) / a

    def time_at(self, s_mm: FloatArray) -> FloatArray:
        """When the move has travelled ``s_mm`` (from its start)."""
        a, v0, v1, peak = self.accel_mm_s2, self.start_mm_s, self.end_mm_s, self.peak_mm_s
        cruise_end_mm = self.distance_mm - self.decel_mm
        accel = (np.sqrt(v0 * v0 + 2 * a * np.maximum(s_mm, 0)) - v0) / a
        cruise = (peak - v0) / a + (s_mm - self.accel_mm) / peak
        left = np.maximum(self.distance_mm - s_mm, 0)
        decel = self.duration_s - (np.sqrt(v1 * v1 + 2 * a * left) - v1) / a
        return np.where(s_mm < self.accel_mm, accel,
                        np.where(s_mm <= cruise_end_mm, cruise, decel))


def ideal_times(move: Trapezoid, steps_per_mm: float) -> FloatArray:
    """Ideal seconds from the move's start of each of its steps (step k at k - ½ steps)."""
    count = round(move.distance_mm * steps_per_mm)
    return move.time_at((np.arange(1, count + 1) - 0.5) / steps_per_mm)


def unslip(edges_cycles: FloatArray, ideal_s: FloatArray, tolerance: int = 400
           ) -> tuple[FloatArray, int]:
    """A move's edges with simavr's lost timer overflows taken out: where the edges jump
    65,536 cycles (± ``tolerance``) against the ideal profile from one step to the next, every
    later edge is put back by that much (the firmware's clock fell behind, not the schedule).
    Returns the edges and how many such jumps there were."""
    residual = edges_cycles - ideal_s * FREQ_HZ
    jumps = np.diff(residual)
    slips = np.zeros_like(edges_cycles)
    found = 0
    for sign in (1, -1):
        where = np.flatnonzero(np.abs(jumps - sign * SLIP_TICKS) <= tolerance)
        found += where.size
        for index in where:
            slips[index + 1:] += sign * SLIP_TICKS
    result: FloatArray = edges_cycles - slips
    return result, found


def step_errors(edges_cycles: FloatArray, ideal_s: FloatArray) -> FloatArray:
    """Each step's edge against its ideal time (µs), one offset (the median) fitted per move."""
    offsets_us = edges_cycles / FREQ_HZ * 1e6 - ideal_s * 1e6
    result: FloatArray = offsets_us - np.median(offsets_us)
    return result


def cruise_ppm(edges_cycles: FloatArray, move: Trapezoid, steps_per_mm: float,
               margin_steps: int = 8) -> float | None:
    """How fast the cruise ran against the commanded speed, in ppm (None: too short a cruise):
    the step interval fitted (least squares) to the steps strictly inside the cruise, less a
    margin, against the commanded one."""
    if move.peak_mm_s < move.speed_mm_s:
        return None
    first = math.ceil(move.accel_mm * steps_per_mm + 0.5) + margin_steps
    last = math.floor((move.distance_mm - move.decel_mm) * steps_per_mm + 0.5) - margin_steps
    if last - first < 50:
        return None
    cruise = edges_cycles[first - 1:last]
    interval = float(np.polyfit(np.arange(cruise.size, dtype=np.float64), cruise, 1)[0])
    ideal = FREQ_HZ / (move.speed_mm_s * steps_per_mm)
    return (ideal / interval - 1) * 1e6


def split_moves(edges: FloatArray, counts: Iterable[int]) -> list[FloatArray]:
    """The edges of each move in turn, given how many steps each makes (an axis' moves)."""
    out, pos = [], 0
    for count in counts:
        out.append(edges[pos:pos + count])
        pos += count
    return out


def percentile(values: Sequence[float] | FloatArray, q: float) -> float:
    array = np.asarray(values, dtype=np.float64)
    return float(np.percentile(array, q)) if array.size else math.nan
