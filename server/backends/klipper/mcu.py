"""One Klipper MCU session over a :class:`~.link.Link`: identify, clock sync, config, watch,
stop and restart, with only the commands stock firmware has.

:meth:`Mcu.connect` reads the data dictionary in chunks (``identify``; bounded, inflated off
the event loop), checks the board is the one served before (name, clock, dictionary), starts
the clock map (``get_uptime`` then a burst of ``get_clock``) and configures a fresh MCU:
``allocate_oids``, the config commands, ``finalize_config`` with a CRC32 of their text. A board
configured by someone else is refused (:class:`KlipperFault`); one still configured by us
(outputs may be on from before) or shut down raises :class:`NeedsRestart`: it is restarted
(:meth:`Mcu.restart`, as Klipper's host does for its ``restart_method``) and connected afresh.
:meth:`Mcu.watch` samples the clock every ``poll_s`` (``BUSY_POLL_S`` while :attr:`Mcu.busy`:
steps queued or an output on; at once on :meth:`Mcu.poll_now`), ``get_config`` every
``CONFIG_EVERY`` polls. Idle, on whole seconds, the ``get_config`` in the clock poll's block
(6 bytes a second, as klippy's); busy, each rides the first block of steps sent a period after
the last (as klippy's do; up to ``RIDE_S`` late), costing no wake-up of its own. Silence for
``timeout_s`` (no block acknowledged), a restart, a clock that jumps ahead, a foreign
configuration or a link fault raise :class:`KlipperFault`, a shutdown (ours from
:meth:`emergency_stop`, or the firmware's own) :class:`McuShutdown`. A restart is told from
the firmware's evidence, never the host's timing: ``starting`` (sent at every boot),
``get_config`` unconfigured, a sequence number never sent, or a clock that went back (checked
against its 64-bit ``get_uptime``); a reading behind the fit is left out of it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import zlib
from collections.abc import Callable
from typing import Any

import serial

from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import Params, ProtocolError
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.link import Link
from server.errors import BackendFault

log = logging.getLogger("motiond.klipper")
Command = tuple[str, dict[str, Any]]
CONNECT_TIMEOUT_S = 2.0  # patience for the first answers: a host busy starting up, a slow USB
IDENTIFY_CHUNK = 40
SYNC_BURST = 8
MAX_DICTIONARY_BYTES = 256 * 1024  # compressed, as served (stock builds: 3-20 kB)
MAX_INFLATED_BYTES = 4 * 1024 * 1024
CLOCK_SETTLE_S = 5.0
RATE_PROBE_S = 0.15
RATE_TOLERANCE = 0.05  # a round trip's jitter over RATE_PROBE_S stays well inside this
RESET_SETTLE_S = 0.015  # klippy's pause after ``reset`` before it lets the port go
POLL_S = 1.0  # a 6-byte get_clock block: 6 bytes/s, as klippy's; the board becoming busy
# wakes the watch (a clock set back as a move begins is read at once, not a second later)
BUSY_POLL_S = 0.4  # while steps are queued or an output is on (15 bytes/s)
CONFIG_EVERY = 8  # get_config once every 8 polls (4 s idle, 3.2 s busy)
CONFIG_RIDE_S = 0.05  # an idle poll's get_config waits this long at most for its get_clock
RIDE_S = 0.15  # while busy, a poll waits this long at most to join a block of steps (5 bytes)
JUMP_S = 0.05  # a clock reading this far outside its round trip's window is looked into
BEHIND_LIMIT_S = 1.0  # a clock that stays behind the fit this long: the fit starts over


class KlipperFault(BackendFault):
    """The MCU cannot be driven (gone, restarted, shut down, misconfigured)."""


class NeedsRestart(KlipperFault):
    """The board must be restarted before it is configured (shut down, or configured by us
    before: its outputs may still be on)."""


class McuShutdown(KlipperFault):
    """The firmware shut down: every output at its default, every queue dropped."""

    def __init__(self, reason: str, clock: int | None, requested: bool) -> None:
        super().__init__(reason)
        self.clock, self.requested = clock, requested


def command_text(command: Command) -> str:
    name, params = command
    return " ".join([name, *(f"{k}={v}" for k, v in params.items())])


def inflate(blob: bytes) -> Dictionary:
    """The dictionary from its zlib text, at most ``MAX_INFLATED_BYTES`` (a bomb is refused)."""
    inflater = zlib.decompressobj()
    try:
        text = inflater.decompress(blob, MAX_INFLATED_BYTES)
        if inflater.unconsumed_tail:
            raise ProtocolError(f"data dictionary inflates beyond {MAX_INFLATED_BYTES} bytes")
        return Dictionary(json.loads(text))
    except (zlib.error, ValueError) as exc:
        raise ProtocolError(f"unreadable data dictionary: {exc}") from exc


def identity(d: Dictionary, blob: bytes) -> dict[str, str]:
    """What makes a board the same board: its MCU, clock and firmware dictionary."""
    return {"MCU": str(d.constants.get("MCU", "?")),
            "CLOCK_FREQ": str(d.constants.get("CLOCK_FREQ", "?")),
            "dictionary": f"{d.version} crc {zlib.crc32(blob):#010x}"}


def arduino_reset(path: str) -> None:
    """Klipper's ``arduino`` restart: DTR toggled (blocking, ~0.3 s: run it off the loop)."""
    port = serial.Serial(path, 2400, timeout=0)
    try:
        port.read(1)
        time.sleep(0.1)
        port.dtr = True
        time.sleep(0.1)
        port.dtr = False
        time.sleep(0.1)
    finally:
        port.close()


class Mcu:
    """See the module docstring."""

    def __init__(self, path: str, baud: int, timeout_s: float, poll_s: float = POLL_S) -> None:
        self.path, self.baud = path, baud
        self.timeout_s, self.poll_s = timeout_s, poll_s
        self.link = Link(path, baud, self._on_message, self._on_link_error)
        self.dictionary = self.link.dictionary
        self.identity: dict[str, str] = {}
        self.clock: ClockSync | None = None
        self.move_count = 0
        self.crc = 0
        self.stopping = False  # an emergency stop we sent: its shutdown is expected
        self.shutdown: McuShutdown | None = None
        self._fault: asyncio.Future[KlipperFault] | None = None
        self._last_heard_s = time.monotonic()
        self._polls = 0
        self._busy = False
        self._nap: asyncio.Future[None] | None = None  # the idle watch's wait, woken by busy
        self._behind_since_s: float | None = None  # the MCU's clock behind the fit since
        self.running = False  # configured by us: a "starting" from now on is a restart
        self._commands: list[Command] = []
        self.on_configured: Callable[[], None] = lambda: None

    # -- connecting ---------------------------------------------------------------------------
    async def connect(self, configure: Callable[[Dictionary], list[Command]],
                      expected: dict[str, str] | None = None,
                      patience_s: float = CONNECT_TIMEOUT_S) -> None:
        """Open, identify, sync the clock and configure; KlipperFault/ProtocolError if not.
        ``expected``: the identity of the board served before (a different one is refused);
        ``patience_s``: how long the first answer may take (longer after a restart)."""
        self._fault = asyncio.get_running_loop().create_future()
        try:
            self.link.open()
        except OSError as exc:
            raise KlipperFault(f"cannot open {self.path}: {exc.strerror}") from exc
        blob = await self._identify(patience_s)
        self.dictionary = await asyncio.to_thread(inflate, blob)
        self.identity = identity(self.dictionary, blob)
        if expected and expected != self.identity:
            diff = ", ".join(f"{k} {expected[k]} -> {v}" for k, v in self.identity.items()
                             if expected.get(k) != v)
            raise KlipperFault(f"a different MCU answers on {self.path} ({diff}): not "
                               "adopted; restart motiond to drive it")
        self.link.dictionary = self.dictionary
        freq = self.dictionary.constant_int("CLOCK_FREQ")
        self.link.window_bytes = self.dictionary.constant_int("RECEIVE_WINDOW", 192)
        await self._start_clock(float(freq))
        self._commands = configure(self.dictionary)
        self.crc = zlib.crc32("\n".join(map(command_text, self._commands)).encode())
        await self._configure()

    async def _ask(self, name: str, response: str, match: Callable[[Params], bool] = lambda _: True,
                   timeout_s: float | None = None, ride_s: float = 0.0,
                   ride_after_s: float = 0.0, **params: Any) -> Params:
        try:
            return await self.link.request(self.dictionary.encode(name, **params), response,
                                           timeout_s or self.timeout_s, match, ride_s,
                                           ride_after_s)
        except TimeoutError as exc:
            raise KlipperFault(f"the MCU on {self.path} does not answer {name}") from exc

    async def _identify(self, patience_s: float) -> bytes:
        blob = bytearray()
        while True:
            offset = len(blob)
            reply = await self._ask("identify", "identify_response",
                                    lambda p, o=offset: p["offset"] == o,  # type: ignore[misc]
                                    max(self.timeout_s, patience_s if not blob else
                                        CONNECT_TIMEOUT_S),
                                    offset=offset, count=IDENTIFY_CHUNK)
            if not reply["data"]:
                return bytes(blob)
            blob += reply["data"]
            if len(blob) > MAX_DICTIONARY_BYTES:
                raise ProtocolError(f"the MCU's data dictionary exceeds {MAX_DICTIONARY_BYTES}"
                                    " bytes")

    async def _start_clock(self, freq_hz: float) -> None:
        await self._steady_clock(freq_hz)
        sent = time.monotonic()
        uptime = await self._ask("get_uptime", "uptime")
        self.clock = ClockSync(freq_hz)
        clock64 = (uptime["high"] << 32) | uptime["clock"]
        self.clock.reset(0.5 * (sent + uptime["#received_s"]), clock64)
        for _ in range(SYNC_BURST):
            await self.sample_clock()

    async def _steady_clock(self, freq_hz: float) -> None:
        """Wait (at most ``CLOCK_SETTLE_S``) until the MCU's clock runs at its CLOCK_FREQ
        (within ``RATE_TOLERANCE``) over ``RATE_PROBE_S``: a board just restarted may not
        yet (a simulated one catching up after its reboot); a fit made then would be wrong."""
        deadline = time.monotonic() + CLOCK_SETTLE_S
        while True:
            first = await self._ask("get_clock", "clock")
            await asyncio.sleep(RATE_PROBE_S)
            second = await self._ask("get_clock", "clock")
            ticks = (second["clock"] - first["clock"]) & 0xFFFFFFFF
            rate = ticks / (second["#received_s"] - first["#received_s"]) / freq_hz
            if abs(rate - 1.0) <= RATE_TOLERANCE:
                return
            if time.monotonic() > deadline:
                raise KlipperFault(f"the MCU's clock runs at {rate:.1%} of its CLOCK_FREQ")

    async def sample_clock(self, ride_after_s: float = 0.0) -> None:
        assert self.clock is not None
        reply = await self._ask("get_clock", "clock", ride_s=self._ride_s(),
                                ride_after_s=ride_after_s)
        sent, received = reply["#sent_s"], reply["#received_s"]
        clock = self.clock.extend(reply["clock"])  # logged with the fit's prediction of it
        log.debug("clock %.6f %.6f %d fit %.6f", sent, received, clock, self.clock.host_at(clock))
        if self.clock.synced:
            off_s = self.clock.predict_error_s(sent, received, reply["clock"])
            if abs(off_s) > JUMP_S and not await self._still_running(off_s, received):
                return  # not a reading of the clock the fit follows
            if abs(off_s) <= JUMP_S:
                self._behind_since_s = None
        self.clock.add_sample(sent, received, clock)

    async def _still_running(self, off_s: float, received_s: float) -> bool:
        """A clock reading far off its window: the firmware's own 64-bit uptime says whether
        its clock went back (a restart: KlipperFault), jumped ahead (no host stall does that:
        KlipperFault) or fell behind, which a board whose clock lost time does (a simulated one
        catching up): not taken into the fit for ``BEHIND_LIMIT_S``, then the fit starts over
        from it (False: skip the reading)."""
        assert self.clock is not None
        last = self.clock.last_clock
        uptime = await self._ask("get_uptime", "uptime")
        clock64 = (uptime["high"] << 32) | uptime["clock"]
        freq = self.clock.freq_hz
        if clock64 < last:
            back_s = (last - clock64) / freq
            raise KlipperFault(f"the MCU restarted: its clock went back {back_s:.3f} s (uptime "
                               f"{clock64 / freq:.3f} s)")
        if off_s > 0.0:
            raise KlipperFault(f"the MCU's clock jumped {off_s * 1e3:.0f} ms ahead of the host's")
        if self._behind_since_s is None:
            self._behind_since_s = received_s
            log.warning("the MCU's clock is %.0f ms behind the host's fit (a board that lost "
                        "time; not a restart)", -off_s * 1e3)
        if received_s - self._behind_since_s < BEHIND_LIMIT_S:
            return False
        self._behind_since_s = None
        self.clock.reset(uptime["#received_s"], clock64)
        return False

    async def _configure(self) -> None:
        config = await self._ask("get_config", "config")
        if config["is_config"] and config["crc"] != self.crc:
            raise KlipperFault(
                f"the MCU is configured differently (crc {config['crc']:#x}, ours "
                f"{self.crc:#x}): restart it (power cycle or reset) before connecting")
        if config["is_shutdown"]:
            raise NeedsRestart("the MCU is shut down")
        if config["is_config"]:
            raise NeedsRestart("the MCU is still configured from before (outputs may be on)")
        self._send_config()
        config = await self._ask("get_config", "config")
        if not config["is_config"] or config["crc"] != self.crc:
            raise KlipperFault("the MCU refused the configuration")
        self.move_count = int(config["move_count"])
        self.running = True
        self.link.ack_timeout_s = self.timeout_s  # a block unacknowledged that long: a fault
        self.on_configured()

    def _send_config(self) -> None:
        encode = self.dictionary.encode
        messages = [encode("allocate_oids", count=self._oid_count())]
        messages += [encode(name, **params) for name, params in self._commands]
        messages.append(encode("finalize_config", crc=self.crc))
        self.link.send(*messages)

    def _oid_count(self) -> int:
        oids = {int(p["oid"]) for _, p in self._commands if "oid" in p}
        return max(oids, default=-1) + 1

    # -- running ------------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        """Steps queued or an output on (set by the backend at its samples)."""
        return self._busy

    @busy.setter
    def busy(self, busy: bool) -> None:
        if busy and self._nap is not None and not self._nap.done():
            self._nap.set_result(None)  # the idle watch polls at once, riding the steps
        self._busy = busy

    def poll_now(self) -> None:
        """A clock reading as soon as may be: a napping watch wakes, a waiting poll leaves."""
        if self._nap is not None and not self._nap.done():
            self._nap.set_result(None)
        self.link.hurry()

    async def watch(self) -> None:
        """Poll clock and config until a fault; raises KlipperFault (McuShutdown)."""
        fault = self._fault
        assert fault is not None
        last_period_s, polled_s = self.poll_s, 0.0
        while True:
            busy = self.busy
            period_s = min(self.poll_s, BUSY_POLL_S) if busy else self.poll_s
            ride_after_s = 0.0
            if busy:  # it rides the first block of steps a period after the last poll (no
                ride_after_s = max(0.0, polled_s + period_s - time.monotonic())  # wake-up)
            else:  # on whole multiples of the period (monotonic), as the other periodic
                # wake-ups of an idle server (the loop monitor's, the kernel's second)
                nap: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
                self._nap = nap
                await asyncio.wait([fault, nap], return_when=asyncio.FIRST_COMPLETED,
                                   timeout=period_s - time.monotonic() % period_s)
                self._nap.cancel()
                if fault.done():
                    raise fault.result()
                if self.busy:  # woken: the first busy poll rides the first steps
                    period_s = BUSY_POLL_S
            # silent past its timeout and the longest wait since the last answer (an idle
            # period's, the first time the board is busy)
            silence_s = self.timeout_s + max(period_s, last_period_s)
            last_period_s = period_s
            self._judge_silence(silence_s)
            await self._poll_unless_fault(ride_after_s)
            polled_s = time.monotonic()

    async def _poll_unless_fault(self, ride_after_s: float) -> None:
        """A poll (see :meth:`_poll`); a fault meanwhile ends it and is raised at once."""
        fault = self._fault
        assert fault is not None
        poll = asyncio.ensure_future(self._poll(ride_after_s))
        either: list[asyncio.Future[Any]] = [fault, poll]
        try:
            await asyncio.wait(either, return_when=asyncio.FIRST_COMPLETED)
        finally:
            poll.cancel()  # (when it has not ended: a fault, or the watch ends)
            if poll.done() and not poll.cancelled():
                poll.exception()  # retrieved: raised below when it is the answer
        if fault.done():  # the first word, with its reason, wins
            raise fault.result()
        try:
            poll.result()
        except (KlipperFault, ConnectionError):
            self.link.read_waiting()  # the board's own word (a shutdown) may be waiting
            if fault.done():
                raise fault.result() from None
            raise

    def _judge_silence(self, silence_s: float) -> None:
        """Raise KlipperFault if nothing came for ``silence_s`` (what came while the host
        hung, the board's own shutdown, is read first: it is the fault then)."""
        assert self._fault is not None
        if time.monotonic() - self._last_heard_s > silence_s:
            self.link.read_waiting()
            if self._fault.done():
                raise self._fault.result()
        if time.monotonic() - self._last_heard_s > silence_s:
            raise KlipperFault(f"the MCU stopped answering for {silence_s:g} s")

    def _ride_s(self) -> float:
        """How long a poll waits to share a block: ``RIDE_S`` while steps flow, else 0."""
        return RIDE_S if self.busy else 0.0

    async def _poll(self, ride_after_s: float = 0.0) -> None:
        self._polls += 1
        if self._polls % CONFIG_EVERY:
            await self.sample_clock(ride_after_s)
            return
        if self.busy:  # each rides a block of steps, one after the other
            await self.sample_clock(ride_after_s)
            config = await self._ask("get_config", "config", ride_s=self._ride_s())
        else:  # the get_config rides in the get_clock's block (7 bytes, not 12)
            asked = asyncio.ensure_future(
                self._ask("get_config", "config", ride_s=CONFIG_RIDE_S))
            await asyncio.sleep(0)  # it waits to ride before the get_clock leaves
            try:
                await self.sample_clock()
            except BaseException:
                asked.cancel()
                raise
            config = await asked
        if config["is_shutdown"]:
            raise self.shutdown or McuShutdown("the MCU shut down: reason unknown", None,
                                               self.stopping)
        if not config["is_config"]:
            raise KlipperFault("the MCU restarted (it lost its configuration)")
        if config["crc"] != self.crc:
            raise KlipperFault("the MCU was configured by someone else")

    def emergency_stop(self) -> None:
        """``emergency_stop`` before everything not yet sent: the firmware drops every queued
        step and output and sets the outputs to their defaults; it stays shut down."""
        if self.link.closed or not self.dictionary.has("emergency_stop"):
            return
        self.stopping = True
        self.link.send_first(self.dictionary.encode("emergency_stop"))

    async def stopped_positions(self, oids: list[int]) -> list[int] | None:
        """Where each stepper stopped (steps since configuration), read from the firmware
        after a shutdown: ``clear_shutdown`` (its queues are empty, outputs at defaults),
        ``stepper_get_position`` each, then ``emergency_stop`` again until the restart.
        None if the board cannot say."""
        try:
            for _ in range(3):
                self.link.send(self.dictionary.encode("clear_shutdown"))
                config = await self._ask("get_config", "config")
                if not config["is_shutdown"]:
                    break
                await asyncio.sleep(0.02)  # still running its shutdown handlers
            else:
                return None
            positions = []
            for oid in oids:
                reply = await self._ask("stepper_get_position", "stepper_position",
                                        lambda p, o=oid: p["oid"] == o,  # type: ignore[misc]
                                        oid=oid)
                positions.append(int(reply["pos"]))
            return positions
        except (KlipperFault, ProtocolError, ConnectionError) as exc:
            log.warning("the MCU on %s cannot say where it stopped: %s", self.path, exc)
            return None
        finally:
            self.emergency_stop()

    async def restart(self, method: str) -> None:
        """Restart the firmware as Klipper's host does (``restart_method``): ``command``
        sends ``reset``, ``arduino`` toggles DTR; the link is closed either way."""
        if method == "command" and not self.link.closed and self.dictionary.has("reset"):
            log.warning("restarting the MCU on %s (reset command)", self.path)
            self.link.send_first(self.dictionary.encode("reset"))  # written at once
            await asyncio.sleep(RESET_SETTLE_S)
            self.link.close()
            return
        self.link.close()
        if method == "arduino" or not self.dictionary.has("reset"):
            log.warning("restarting the MCU on %s (DTR toggle)", self.path)
            try:
                await asyncio.to_thread(arduino_reset, self.path)
            except (OSError, serial.SerialException, ValueError) as exc:
                log.warning("cannot toggle DTR on %s: %s", self.path, exc)

    def _on_message(self, name: str, params: Params, now_s: float) -> None:
        self._last_heard_s = now_s
        if name == "starting" and self.running:  # the firmware says it at every boot
            self._report(KlipperFault("the MCU restarted (it said 'starting')"))
        if name in ("shutdown", "is_shutdown"):
            reason = str(params.get("static_string_id", "?"))
            jump = self._clock_jump(params.get("clock"), now_s)
            if jump is not None:
                self._report(KlipperFault(f"{jump}; it shut down: {reason}"))
                return
            if self.shutdown is None:
                clock = params.get("clock")
                self.shutdown = McuShutdown(f"the MCU shut down: {reason}",
                                            None if clock is None else int(clock),
                                            self.stopping)
            self._report(self.shutdown)

    def _clock_jump(self, clock32: int | None, now_s: float) -> str | None:
        """What is wrong with a clock the MCU reported, if it cannot be its running clock:
        earlier than one it reported before (it started over), or ``JUMP_S`` ahead of the fit.
        A late one is not a jump: a busy host may read a message well after it was sent."""
        if clock32 is None or self.clock is None or not self.clock.synced:
            return None
        clock = self.clock.extend(clock32)
        freq, last = self.clock.freq_hz, self.clock.last_clock
        ahead_s = (clock - self.clock.clock_at(now_s)) / freq
        if clock < last:
            return f"the MCU restarted: its clock went back {(last - clock) / freq:.3f} s"
        if ahead_s > JUMP_S:
            return f"the MCU's clock jumped {ahead_s * 1e3:.0f} ms ahead of the host's"
        return None

    def _on_link_error(self, reason: str) -> None:
        self._report(KlipperFault(reason))

    def _report(self, fault: KlipperFault) -> None:
        if self._fault is not None and not self._fault.done():
            self._fault.set_result(fault)

    def close(self) -> None:
        self.link.close()


__all__ = ["KlipperFault", "Mcu", "McuShutdown", "NeedsRestart", "ProtocolError", "command_text"]
