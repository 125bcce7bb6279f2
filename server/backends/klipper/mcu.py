"""One Klipper MCU session over a :class:`~.link.Link`: identify, clock sync, config, watch.

:meth:`Mcu.connect` reads the data dictionary in chunks (``identify``), starts the clock map
(``get_uptime`` then a burst of ``get_clock``), and configures the MCU: ``allocate_oids``, the
config commands, ``finalize_config`` with a CRC32 of their text. An MCU that is already
configured is reused only when its CRC is ours; one configured differently is refused (it would
be driven with a stale config); one shut down (after a fault) is reset with ``config_reset``
and configured afresh. :meth:`Mcu.watch` then samples the clock every
``poll_s`` and checks ``get_config``: an MCU silent for ``timeout_s``, restarted (unconfigured,
a clock jump or a sequence number never sent) or shut down raises :class:`KlipperFault` naming
the reason. An emergency stop the host asked for is followed by ``config_reset`` and the same
configuration at once, so the machine can move again right away.
"""

from __future__ import annotations

import asyncio
import logging
import time
import zlib
from collections.abc import Callable
from typing import Any

from server.backends.klipper.clocksync import ClockSync
from server.backends.klipper.codec import Params, ProtocolError
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.link import Link

log = logging.getLogger("motiond.klipper")
Command = tuple[str, dict[str, Any]]
CONNECT_TIMEOUT_S = 2.0  # patience for the first answers: a host busy starting up, a slow USB
IDENTIFY_CHUNK = 40
SYNC_BURST = 8


class KlipperFault(Exception):
    """The MCU cannot be driven (gone, restarted, shut down, misconfigured)."""


def command_text(command: Command) -> str:
    name, params = command
    return " ".join([name, *(f"{k}={v}" for k, v in params.items())])


class Mcu:
    """See the module docstring."""

    def __init__(self, path: str, baud: int, timeout_s: float, poll_s: float = 0.2) -> None:
        self.path, self.baud = path, baud
        self.timeout_s, self.poll_s = timeout_s, poll_s
        self.link = Link(path, baud, self._on_message, self._on_link_error)
        self.dictionary = self.link.dictionary
        self.clock: ClockSync | None = None
        self.move_count = 0
        self.crc = 0
        self.stopping = False  # an emergency stop we sent: its shutdown is expected
        self._stops = 0  # emergency stops sent: a reply to a query asked before one is stale
        self.shutdown_reason: str | None = None
        self._fault: asyncio.Future[str] | None = None
        self._last_heard_s = time.monotonic()
        self._commands: list[Command] = []
        self.on_configured: Callable[[], None] = lambda: None

    # -- connecting ---------------------------------------------------------------------------
    async def connect(self, configure: Callable[[Dictionary], list[Command]]) -> None:
        """Open, identify, sync the clock and configure; KlipperFault/ProtocolError if not."""
        self._fault = asyncio.get_running_loop().create_future()
        try:
            self.link.open()
        except OSError as exc:
            raise KlipperFault(f"cannot open {self.path}: {exc.strerror}") from exc
        self.dictionary = Dictionary.from_compressed(await self._identify())
        self.link.dictionary = self.dictionary
        freq = self.dictionary.constant_int("CLOCK_FREQ")
        self.link.window.window_bytes = self.dictionary.constant_int("RECEIVE_WINDOW", 192)
        await self._start_clock(float(freq))
        self._commands = configure(self.dictionary)
        self.crc = zlib.crc32("\n".join(map(command_text, self._commands)).encode())
        await self._configure()

    async def _ask(self, name: str, response: str, match: Callable[[Params], bool] = lambda _: True,
                   timeout_s: float | None = None, **params: Any) -> Params:
        try:
            return await self.link.request(self.dictionary.encode(name, **params), response,
                                           timeout_s or self.timeout_s, match)
        except TimeoutError as exc:
            raise KlipperFault(f"the MCU on {self.path} does not answer {name}") from exc

    async def _identify(self) -> bytes:
        blob = bytearray()
        while True:
            offset = len(blob)
            reply = await self._ask("identify", "identify_response",
                                    lambda p, o=offset: p["offset"] == o,  # type: ignore[misc]
                                    max(self.timeout_s, CONNECT_TIMEOUT_S),
                                    offset=offset, count=IDENTIFY_CHUNK)
            if not reply["data"]:
                return bytes(blob)
            blob += reply["data"]

    async def _start_clock(self, freq_hz: float) -> None:
        sent = time.monotonic()
        uptime = await self._ask("get_uptime", "uptime")
        self.clock = ClockSync(freq_hz)
        clock64 = (uptime["high"] << 32) | uptime["clock"]
        self.clock.reset(0.5 * (sent + uptime["#received_s"]), clock64)
        for _ in range(SYNC_BURST):
            await self.sample_clock()

    async def sample_clock(self) -> None:
        assert self.clock is not None
        sent = time.monotonic()
        reply = await self._ask("get_clock", "clock")
        received = reply["#received_s"]
        if self.clock.synced and self.clock.predict_error_s(sent, received, reply["clock"]) > 0.05:
            raise KlipperFault("the MCU clock jumped: the MCU restarted")
        self.clock.add_sample(sent, received, self.clock.extend(reply["clock"]))

    async def _configure(self) -> None:
        config = await self._ask("get_config", "config")
        if config["is_config"] and config["crc"] != self.crc:
            raise KlipperFault(
                f"the MCU is configured differently (crc {config['crc']:#x}, ours "
                f"{self.crc:#x}): restart it (power cycle or reset) before connecting")
        if config["is_shutdown"]:  # ours, or unconfigured: start it over (the alarm stays)
            log.warning("the MCU on %s is shut down: resetting its configuration", self.path)
            self.link.send(self.dictionary.encode("config_reset"))
            config["is_config"] = 0
        if not config["is_config"]:
            self._send_config()
            config = await self._ask("get_config", "config")
            if not config["is_config"] or config["crc"] != self.crc:
                raise KlipperFault("the MCU refused the configuration")
        self.move_count = int(config["move_count"])
        self.on_configured()

    def _send_config(self) -> None:
        encode = self.dictionary.encode
        messages = [encode("allocate_oids", count=self._oid_count())]
        messages += [encode(name, **params) for name, params in self._commands]
        messages.append(encode("finalize_config", crc=self.crc))
        for message in messages:
            self.link.send(message)

    def _oid_count(self) -> int:
        oids = {int(p["oid"]) for _, p in self._commands if "oid" in p}
        return max(oids, default=-1) + 1

    # -- running ------------------------------------------------------------------------------
    async def watch(self) -> None:
        """Poll clock and config until a fault; raises KlipperFault with the reason."""
        assert self._fault is not None
        while True:
            done, _ = await asyncio.wait([self._fault], timeout=self.poll_s)
            if done:
                raise KlipperFault(self._fault.result())
            if time.monotonic() - self._last_heard_s > self.timeout_s:
                raise KlipperFault(f"the MCU stopped answering for {self.timeout_s:g} s")
            try:
                await self._poll()
            except KlipperFault:
                if self._fault.done():  # the first word, with its reason, wins
                    raise KlipperFault(self._fault.result()) from None
                raise

    async def _poll(self) -> None:
        stops = self._stops
        poll = asyncio.gather(self.sample_clock(), self._ask("get_config", "config"))
        _, config = await poll
        if self._stops != stops:  # asked before the latest emergency stop: says nothing of it
            return
        if self.stopping:
            self.stopping = not (config["is_config"] and not config["is_shutdown"])
            return
        if config["is_shutdown"]:
            raise KlipperFault(f"the MCU shut down: {self.shutdown_reason or 'reason unknown'}")
        if not config["is_config"]:
            raise KlipperFault("the MCU restarted (it lost its configuration)")
        if config["crc"] != self.crc:
            raise KlipperFault("the MCU was configured by someone else")

    def emergency_stop(self) -> None:
        """``emergency_stop`` now (every queued step and output dropped, outputs to their
        defaults), then ``config_reset`` and the same configuration, sent in order at once."""
        self.stopping = True
        self._stops += 1
        self.link.send_first(self.dictionary.encode("emergency_stop"))
        self.link.send(self.dictionary.encode("config_reset"))
        self._send_config()
        self.on_configured()

    def _on_message(self, name: str, params: Params, now_s: float) -> None:
        self._last_heard_s = now_s
        if name in ("shutdown", "is_shutdown"):
            reason = params.get("static_string_id", "?")
            self.shutdown_reason = str(reason)
            if self._clock_jumped(params.get("clock"), now_s):
                self._report("the MCU restarted (its clock started over)")
            elif not self.stopping:
                self._report(f"the MCU shut down: {reason}")

    def _clock_jumped(self, clock32: int | None, now_s: float) -> bool:
        """Whether a clock the MCU reported cannot be its running clock: earlier than one it
        reported before (it started over), or 50 ms ahead of the fit. A late one is not a
        jump: a busy host may read a message well after it was sent."""
        if clock32 is None or self.clock is None or not self.clock.synced:
            return False
        clock = self.clock.extend(clock32)
        ahead = clock - self.clock.clock_at(now_s)
        return clock < self.clock.last_clock or ahead > 0.05 * self.clock.freq_hz

    def _on_link_error(self, reason: str) -> None:
        self._report(reason)

    def _report(self, reason: str) -> None:
        if self._fault is not None and not self._fault.done():
            self._fault.set_result(reason)

    def close(self) -> None:
        self.link.close()


__all__ = ["KlipperFault", "Mcu", "ProtocolError", "command_text"]
