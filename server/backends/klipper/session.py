"""The Klipper backend's session with the board: connect, configure, watch, stop, recover.

:class:`BoardSession` is the part of :class:`~.backend.KlipperBackend` (a base class of it) that
owns the board's connection (:class:`~.mcu.Mcu`, through its :class:`~.link.Link`) and the
backend's task (:meth:`BoardSession.run`): connecting, configuring (afresh after every
restart), watching the board and reconnecting every ``retry_s`` after a fault.

Stopping: halt (alarm, M112, Ctrl-X) sends ``emergency_stop`` at once when the MCU has anything
queued or an output on, and so does every fault while the board can still hear. A shut-down
board stays so (the machine in ALARM, every move refused) until :meth:`BoardSession.recover`
(``$X``, M999): where each stepper stopped is read from the firmware first and becomes the
machine position (``relocate``), then the board is restarted (``restart_method``) and
configured afresh. A fault (:class:`~.mcu.KlipperFault`) is raised once from the next
``sample``, which the machine turns into an alarm; the backend then reconnects every
``retry_s``.

Apart from the steps (:mod:`.schedule`) and the outputs (:mod:`.outputs`) because it runs on the
board's events and the machine's commands, never per piece or per sample. Its state is the
backend's, created by ``KlipperBackend.__init__``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from server.backends.klipper.codec import ProtocolError
from server.backends.klipper.dictionary import Dictionary
from server.backends.klipper.mcu import (
    CONNECT_TIMEOUT_S,
    Command,
    KlipperFault,
    Mcu,
    McuShutdown,
    NeedsRestart,
)
from server.backends.klipper.movequeue import MoveQueue
from server.backends.klipper.pins import Axis, Output, config_commands
from server.backends.klipper.printclock import PrintClock
from server.errors import CommandError, Error

if TYPE_CHECKING:
    from server.config import BackendConfig

log = logging.getLogger("motiond.klipper")
EXIT_GRACE_S = 0.3
RESTART_WAIT_S = 0.3  # a restarted board boots before it is asked who it is
RESTART_PATIENCE_S = 10.0  # a restarted board's first answer (a bootloader, a slow boot)
RECOVER_TIMEOUT_S = 20.0  # $X waits this long for a restarted board to be configured
STOP_FLUSH_S = 0.1  # a fault's emergency stop gets this long to leave before the link closes
STOP_READ_S = 0.5  # reading where a shut-down board stopped (a few round trips) takes at most


class BoardSession:
    """The board's connection, faults, stops and restarts; see the module docstring."""

    # The backend's state this part reads and writes (set by KlipperBackend.__init__).
    cfg: BackendConfig
    retry_s: float
    axes: list[Axis]
    outputs: dict[str, Output]
    mcu: Mcu | None
    ready: bool
    fault: str | None
    _fault_to_raise: str | None
    identity: dict[str, str]
    shut_down: bool
    _recover: asyncio.Event
    _configured: asyncio.Event
    _config_base: list[int]
    motors_on: bool
    _enable_clock: int
    _queue: MoveQueue
    _print: PrintClock
    relocate: Callable[[Sequence[float]], None]
    _wake: Callable[[], None]

    if TYPE_CHECKING:
        def _busy(self) -> bool: ...  # the schedule's
        def _drop_motion(self) -> None: ...

    async def recover(self) -> None:
        """``$X``/M999: a shut-down board is restarted and configured afresh (waited for);
        CommandError while the board is not there or does not come back."""
        if self.ready and not self.shut_down:
            return
        if not self.shut_down:
            raise CommandError(Error.LOCKED_OUT, self.fault or
                               f"the MCU on {self.cfg.serial} is not connected yet")
        self._recover.set()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._configured.wait(), RECOVER_TIMEOUT_S)
        if not self.ready:
            raise CommandError(Error.LOCKED_OUT, "the MCU did not come back after its restart"
                               + (f": {self.fault}" if self.fault else ""))

    def halt(self) -> None:
        busy = self._busy()
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0
        if busy and self.mcu is not None and self.ready:
            log.warning("emergency stop sent to the MCU")
            self._mark_shut_down()  # nothing more goes out: the board is stopping
            self.mcu.emergency_stop()

    def _mark_shut_down(self) -> None:
        """The board is (about to be) shut down: nothing is sent until recover() restarts it."""
        self.ready, self.shut_down = False, True
        self._configured.clear()

    def close(self) -> None:
        if self.mcu is not None:
            if self.ready and self._busy():
                self.mcu.emergency_stop()
            self.mcu.close()
            self.mcu = None
        self.ready = False

    # -- the owned task -----------------------------------------------------------------------
    async def run(self) -> None:
        """Connect, configure and watch the MCU; on a fault stop the board, report it and
        reconnect; a shut-down board waits for :meth:`recover`, then is restarted."""
        restarted = False
        while True:
            mcu = Mcu(str(self.cfg.serial), self.cfg.baud, self.cfg.response_timeout_s)
            mcu.on_configured = self._on_configured
            self.mcu = mcu
            delay = self.retry_s
            try:
                await mcu.connect(self._config_commands, self.identity,
                                  RESTART_PATIENCE_S if restarted else CONNECT_TIMEOUT_S)
                self.identity = mcu.identity
                self.ready, self.fault, self.shut_down, restarted = True, None, False, False
                self._recover.clear()  # a $X that came while it was away is answered now
                self._configured.set()
                log.info("MCU on %s ready (%s, %s)", self.cfg.serial,
                         mcu.dictionary.constants.get("MCU"), mcu.dictionary.version)
                await mcu.watch()
            except NeedsRestart as exc:
                self.ready = False
                if restarted:
                    self._on_fault(f"{exc}, even after a restart")
                else:
                    log.warning("MCU on %s: %s: restarting it", self.cfg.serial, exc)
                    await mcu.restart(self.cfg.restart_method)
                    restarted, delay = True, RESTART_WAIT_S
            except McuShutdown as exc:
                await self._after_shutdown(mcu, exc)
                restarted, delay = True, RESTART_WAIT_S
            except (KlipperFault, ProtocolError, ConnectionError) as exc:
                if self.ready or self.shut_down:  # ours: outputs off first, if it still hears
                    mcu.emergency_stop()
                self.ready = False
                self._on_fault(str(exc))
                await self._drain(mcu, STOP_FLUSH_S)
            except asyncio.CancelledError:
                await self._stop_before_exit(mcu)
                raise
            finally:
                self.ready = False
                mcu.close()
            await asyncio.sleep(delay)

    async def _after_shutdown(self, mcu: Mcu, shutdown: McuShutdown) -> None:
        """The board shut down (our emergency stop or its own fault): read where it stopped,
        make that the machine position, alarm, and wait for :meth:`recover` to restart it."""
        self._mark_shut_down()
        cause = "emergency stop" if shutdown.requested else str(shutdown)
        self.fault = f"klipper MCU on {self.cfg.serial}: {cause}"  # what a new move is told
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0
        try:  # a board that stopped answering as it shut down: the alarm does not wait
            positions = await asyncio.wait_for(
                mcu.stopped_positions([axis.oid for axis in self.axes]), STOP_READ_S)
        except TimeoutError:
            positions = None
        if positions is None:
            where = "where it stopped is unknown"
        else:
            for axis, base, steps in zip(self.axes, self._config_base, positions, strict=True):
                axis.position = base + (-steps if axis.invert_dir else steps)
            stopped = [axis.position / axis.steps_per_mm for axis in self.axes]
            where = "stopped at " + " ".join(
                f"{axis.name.upper()}{mm:.3f}" for axis, mm in zip(self.axes, stopped,
                                                                    strict=True))
            self.relocate(stopped)
        self._on_fault(f"{cause}; {where} (position may be lost: re-home); $X or M999 "
                       "restarts the MCU")
        await self._recover.wait()
        self._recover.clear()
        await mcu.restart(self.cfg.restart_method)

    async def _drain(self, mcu: Mcu, limit_s: float) -> bool:
        """Wait (at most ``limit_s``) until what was queued for the MCU has left."""
        deadline = time.monotonic() + limit_s
        while (mcu.link.queued_bytes or mcu.link.in_flight) and not mcu.link.closed:
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.01)
        return True

    async def _stop_before_exit(self, mcu: Mcu) -> None:
        """Shutting down with steps queued or a tool on: the emergency stop gets out first
        (bounded: at most ``EXIT_GRACE_S``)."""
        mcu.link.rest()  # no more ticks: acknowledgements are read as they arrive
        if not (self.ready and self._busy()):
            return
        mcu.emergency_stop()
        if not await self._drain(mcu, EXIT_GRACE_S):
            log.error("the MCU did not acknowledge the emergency stop before exit")

    def _on_fault(self, reason: str) -> None:
        message = f"klipper MCU on {self.cfg.serial}: {reason}"
        if message != self.fault:
            log.error("%s", message)
            pending = self._fault_to_raise  # the cause leads until the next tick raises it
            self._fault_to_raise = message if pending is None else f"{pending}; then {reason}"
            self._wake()  # raised from the next sample(), even on a resting machine
        self.fault = message
        self._drop_motion()
        for out in self.outputs.values():
            out.value = 0.0

    def _on_configured(self) -> None:
        self.motors_on, self._enable_clock = True, 0  # the configuration turns them on
        for axis in self.axes:
            axis.steps.restart()
        self._config_base = [axis.position for axis in self.axes]
        for out in self.outputs.values():
            out.last_clock, out.value = 0, 0.0
        self._queue.free_slots()
        self._print.unanchor()

    def _config_commands(self, d: Dictionary) -> list[Command]:
        return config_commands(self.cfg, self.axes, self.outputs, d)
