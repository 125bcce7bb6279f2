"""The core's command set: Grbl's ``$`` commands and Smoothie/RepRap named and M commands.

Registered on the dispatcher by :func:`register_core_commands`. ``$J=`` jogs plan like any
move in their own state; ``$C`` toggles check mode (lines run through the interpreter, nothing
moves; leaving it resets the modal state as Grbl does).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from server import __version__
from server.errors import CommandError, Error
from server.gcode.codes import CodeCall
from server.gcode.parser import parse_line
from server.motion.moves import Output, Sync, SyncKind
from server.protocol.lines import OK_PREFIX
from server.protocol.reports import (
    format_build_info,
    format_help,
    format_settings,
    sender_blocks,
)
from server.runtime.dispatcher import Command, Dispatcher, Handler
from server.runtime.events import MachineState

if TYPE_CHECKING:
    from server.kernel.kernel import Kernel

BANNER_VERSION = "1.1h"
# M115's capability report: what RepRap hosts may rely on. EMERGENCY_PARSER: M112 and M410 act
# the moment they arrive (OctoPrint then sends them ahead of its queue). BUSY_PROTOCOL: a held
# ok is preceded by ``echo:busy: processing`` every 2 s, or as often as M113 S<seconds> says.
CAPABILITIES: dict[str, bool] = {
    "EMERGENCY_PARSER": True,
    "BUSY_PROTOCOL": True,
    "AUTOREPORT_TEMP": False,
    "AUTOREPORT_POS": False,
    "SDCARD": False,
    "EXTENDED_M20": False,
}


class CoreCommands:
    """Handlers bound to one kernel."""

    def __init__(self, kernel: Kernel) -> None:
        self.kernel = kernel
        self.machine = kernel.machine
        self.startup_lines: dict[int, str] = {}

    def register(self, dispatcher: Dispatcher) -> None:
        queries: dict[str, Handler] = {
            "$": self.help,
            "$$": self.settings,
            "$#": self.offsets,
            "$G": self.modal,
            "$I": self.build_info,
            "$N": self.startup,
            "version": self.version,
        }
        for name, handler in queries.items():
            dispatcher.register(name, handler, when_locked=True, query=True)
        locked_ok: dict[str, Handler] = {
            "$=": self.write_setting,
            "$N0=": self.startup_set,
            "$N1=": self.startup_set,
            "$C": self.check_mode,
            "$X": self.unlock,
            "$RST=": self.restore,
            "$SLP": self.sleep,
        }
        for name, handler in locked_ok.items():
            dispatcher.register(name, handler, when_locked=True)
        dispatcher.register("$J=", self.jog)
        dispatcher.register("M113", self.keepalive, when_locked=True)
        dispatcher.register("M117", self.display, when_locked=True)
        dispatcher.register("M118", self.echo, when_locked=True)
        codes = self.machine.codes
        codes.register("core", 105, self.temperature, query=True)
        codes.register("core", 115, self.firmware_info, query=True)

    def register_fallbacks(self, dispatcher: Dispatcher) -> None:
        """Answers for what no module took: ``$H`` without an ``[endstops]`` section."""
        if "$H" not in dispatcher.names():
            dispatcher.register("$H", self.no_homing, when_locked=True)

    def no_homing(self, command: Command) -> None:
        raise CommandError(
            Error.SETTING_DISABLED, "homing is not configured: add an [endstops] section"
        )

    def help(self, command: Command) -> list[str]:
        return [format_help()]

    async def settings(self, command: Command) -> list[str]:
        board = await self.machine.board_answer(command)
        return board if board is not None else format_settings(self.machine.settings.values())

    async def write_setting(self, command: Command) -> list[str]:
        return await self.machine.write_setting(command)

    async def offsets(self, command: Command) -> list[str]:
        board = await self.machine.board_answer(command)
        return board if board is not None else self.machine.interpreter.offsets_report()

    async def modal(self, command: Command) -> list[str]:
        board = await self.machine.board_answer(command)
        return board if board is not None else [self.machine.interpreter.gc_report()]

    async def build_info(self, command: Command) -> list[str]:
        board = await self.machine.board_answer(command)
        if board is not None:
            return board
        core = self.kernel.config.core
        return format_build_info(
            f"{BANNER_VERSION}.motiond-{__version__}",
            sender_blocks(core.planner.max_blocks, core.planner.max_blocks),
            core.protocol.rx_buffer_bytes,
        )

    async def startup(self, command: Command) -> list[str]:
        board = await self.machine.board_answer(command)
        if board is not None:
            return board
        return [f"$N{n}={self.startup_lines.get(n, '')}" for n in (0, 1)]

    async def startup_set(self, command: Command) -> list[str] | None:
        board = await self.machine.board_answer(command)
        if board is not None:
            return board
        index = int(command.name[2])
        text = command.args.strip()
        if text:
            line = parse_line(text)
            if line.error is not None:
                raise line.error
        self.startup_lines[index] = text
        return None

    def check_mode(self, command: Command) -> list[str]:
        kernel = self.kernel
        if kernel.state is MachineState.CHECK:
            self.machine.leave_check_mode()
            return ["[MSG:Disabled]"]
        if kernel.state is not MachineState.IDLE or not self.machine.stepgen.idle:
            raise CommandError(Error.NOT_IDLE, "check mode needs an idle machine")
        self.machine.enter_check_mode()
        return ["[MSG:Enabled]"]

    async def unlock(self, command: Command) -> None:
        await self.machine.unlock()

    def restore(self, command: Command) -> None:
        target = command.args.strip()
        if target not in ("$", "#", "*"):
            raise CommandError(Error.INVALID_STATEMENT, "use $RST=$, $RST=# or $RST=*")
        if target in ("$", "*"):
            self.machine.restore_settings()
        if target in ("#", "*"):
            self.machine.clear_offsets()

    def sleep(self, command: Command) -> None:
        if not self.machine.stepgen.idle:
            raise CommandError(Error.NOT_IDLE, "sleep needs an idle machine")
        self.machine.stop_now()
        self.machine.motors(False)
        self.kernel.set_state(MachineState.SLEEP)
        self.kernel.push("[MSG:Sleeping]")

    async def jog(self, command: Command) -> None:
        state = self.kernel.state
        if state not in (MachineState.IDLE, MachineState.JOG):
            raise CommandError(Error.NOT_IDLE, "jog needs an idle machine")
        line = parse_line(command.args)
        if line.error is not None:
            raise CommandError(Error.INVALID_JOG, f"invalid jog: {line.error.message}")
        await self.machine.jog(command, line)

    def version(self, command: Command) -> list[str]:
        name = self.kernel.config.core.machine.name
        return [
            f"Build version: motiond-{__version__}, Build date: -, MCU: python, "
            f"System Clock: -, Grbl {BANNER_VERSION} compatible, machine: {name}"
        ]

    def temperature(self, call: CodeCall) -> list[Output]:
        """M105 (RepRap hosts poll it): no heaters here. Marlin's one line, ``ok T:..``
        (a RepRap host's ok line carries it; a Grbl sender gets it as a line before ``ok``)."""
        return [Sync(SyncKind.MESSAGE, {"lines": [OK_PREFIX + "T:0.0 /0.0 B:0.0 /0.0"]})]

    def firmware_info(self, call: CodeCall) -> list[Output]:
        """M115: the firmware line and Marlin's capability report (``Cap:NAME:0|1``)."""
        text = (
            f"FIRMWARE_NAME:motiond {__version__} (Grbl {BANNER_VERSION} compatible) "
            "PROTOCOL_VERSION:1.0 MACHINE_TYPE:laser/cnc EXTRUDER_COUNT:0"
        )
        caps = [f"Cap:{name}:{int(value)}" for name, value in CAPABILITIES.items()]
        return [Sync(SyncKind.MESSAGE, {"lines": [text, *caps]})]

    def display(self, command: Command) -> None:
        """M117 <text>: the display message; every connection gets it as ``[MSG:<text>]``."""
        text = _message_text(command.args)
        if text:
            self.kernel.push(f"[MSG:{text}]")

    def keepalive(self, command: Command) -> list[str]:
        """M113 [S<seconds>]: how often this connection hears ``echo:busy: processing`` while
        an ok is held (Marlin's host keep-alive: 0 off, at most 60 s); bare M113 reports it."""
        words = command.args.split()
        current = getattr(command.source, "busy_interval_s", None)
        if not words:
            return [f"echo:M113 S{current:g}" if current is not None else "echo:M113 off"]
        value = words[0][1:] if words[0][:1] in ("S", "s") and len(words) == 1 else ""
        try:
            seconds = float(value)
        except ValueError:
            raise CommandError(Error.BAD_NUMBER_FORMAT, "M113 takes S<seconds>") from None
        if not 0.0 <= seconds <= 60.0:
            raise CommandError(Error.BAD_NUMBER_FORMAT, "M113 S: 0 to 60 seconds")
        if current is not None:
            command.source.busy_interval_s = seconds  # type: ignore[attr-defined]
        return []

    def echo(self, command: Command) -> list[str]:
        """M118 [E1] [A1] <text>: the text back to the sender, as ``echo:<text>`` (Marlin's E1
        form: a bare text could read as a reply)."""
        words = command.args.split(maxsplit=1)
        if words and words[0].upper() in ("E1", "A1", "E0", "A0", "PN0", "PN1"):
            words = words[1:]
        return [f"echo:{_message_text(words[0] if words else '')}"]


def _message_text(text: str) -> str:
    """One line of display text, safe inside ``[MSG:...]``."""
    return " ".join(text.replace("]", ")").split())[:100]
