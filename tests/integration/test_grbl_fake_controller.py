"""The grbl backend against a scripted controller over TCP (FluidNC and grblHAL offer Grbl on a
socket): what a motiond controller never does — stay silent until Ctrl-X, report a bigger
receive buffer in ``Bf:``, answer an error number outside Grbl 1.1's table, restart by itself,
run on after a ``!`` (grblHAL's rig does, now and then, right after a resume).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

from server.app import App
from server.backends.grbl.machine import GrblMachine
from server.config_loader import build_config
from server.runtime.clock import RealClock
from server.runtime.events import MachineState
from server.sessions.input import INBOUND_LINES
from server.sessions.session import Session
from server.transports.tcp import TcpTransport
from tests.support.helpers import running
from tests.support.senders import BANNER as MOTIOND_BANNER
from tests.support.senders import CharCountingClient, wait_for

BANNER = b"\r\nGrbl 3.7 [FluidNC v3.7.8 (wifi) '$' for help]\r\n"
SETTINGS = {100: 160.0, 101: 160.0, 110: 6000.0, 111: 6000.0, 120: 500.0, 121: 500.0,
            130: 200.0, 131: 150.0, 11: 0.02, 32: 1.0}


class FakeController:
    """A Grbl controller on a socket, scripted; records the lines it receives."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.resets = 0
        self.mute_next_reset = False  # hang on the next Ctrl-X: no banner
        self.connections = 0
        self.held: list[bytes] = []  # answers held back while ``holding``
        self.holding = False
        self.offsets: list[str] = []  # its $# report, before the ok
        self.writer: asyncio.StreamWriter | None = None
        self.server: asyncio.Server | None = None
        self.report = b"<Idle|MPos:0.000,0.000|Bf:15,255|FS:0,0>\r\n"  # its answer to '?'
        self.next_reports: list[bytes] = []  # answers to the next polls, before ``report``
        self.polls_answered = True
        self.noise = b""  # written before each report (a noisy line, a chatty board)
        self.refused: dict[str, int] = {}  # lines it answers with error:N
        self.realtime = bytearray()  # the '!' and '~' it received, in order

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._serve, "127.0.0.1", 0)
        port: int = self.server.sockets[0].getsockname()[1]
        return port

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writer = writer  # silent: no banner until Ctrl-X (as FluidNC on a socket)
        self.connections += 1
        pending = b""
        while data := await reader.read(4096):
            pending += data
            if b"\x18" in pending:
                self.resets += 1
                pending = pending.rpartition(b"\x18")[2]
                self.held.clear()  # a reset empties the board's buffer: never answered
                self.holding = False
                self.lines.append("<reset>")
                if not self.mute_next_reset:
                    writer.write(BANNER)
                self.mute_next_reset = False
            self.realtime += bytes(b for b in pending if b in b"!~")
            pending = pending.replace(b"!", b"").replace(b"~", b"")
            if b"?" in pending:
                pending = pending.replace(b"?", b"")
                if self.polls_answered:
                    writer.write(self.noise)
                    writer.write(self.next_reports.pop(0) if self.next_reports else self.report)
            *lines, pending = pending.split(b"\n")
            for line in lines:
                answer = self._answer(line.decode().strip())
                if self.holding:
                    self.held.append(answer)  # a full planner: Grbl answers in order, later
                else:
                    writer.write(answer)

    def _answer(self, line: str) -> bytes:
        self.lines.append(line)
        if line == "$$":
            return "".join(f"${n}={v:.3f}\r\n" for n, v in SETTINGS.items()).encode() + b"ok\r\n"
        if line == "$#":
            return "".join(f"{text}\r\n" for text in self.offsets).encode() + b"ok\r\n"
        if line == "$G":
            return b"[GC:G0 G54 G17 G21 G90 G94 M5 M9 T0 F0 S0]\r\nok\r\n"
        if line == "G0X3":
            return b"error:79\r\n"  # a grblHAL number Grbl 1.1 does not have
        if line in self.refused:
            return f"error:{self.refused[line]}\r\n".encode()
        return b"ok\r\n"

    def release(self) -> None:
        assert self.writer is not None
        self.holding = False
        self.writer.write(b"".join(self.held))
        self.held.clear()

    def restart(self) -> None:
        assert self.writer is not None
        self.writer.write(BANNER)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.server is not None:
            self.server.close()


@contextlib.asynccontextmanager
async def linked(tmp_path: Path, reply_timeout_s: float = 10.0, offsets: tuple[str, ...] = (),
                 reports: tuple[bytes, ...] = ()) -> AsyncIterator[tuple[FakeController, App]]:
    fake = FakeController()
    fake.offsets = list(offsets)
    fake.next_reports = list(reports)
    port = await fake.start()
    config = build_config({
        "axes": {axis: {"steps_per_mm": 80, "max_rate_mm_s": 100, "accel_mm_s2": 1000,
                        "max_mm": 300} for axis in "xy"},
        "jobs": {"data_dir": str(tmp_path / "data")}, "tcp": {"port": 0},
        "backend": {"kind": "grbl", "tcp": f"127.0.0.1:{port}", "banner_timeout_s": 0.2,
                    "status_hz": 20, "reply_timeout_s": reply_timeout_s, "reconnect_s": 0.1}})
    try:
        async with running(config, RealClock(), [TcpTransport]) as app:
            machine = app.kernel.machine
            assert isinstance(machine, GrblMachine)
            await wait_for(lambda: machine.controller.ready, 5.0, "the handshake")
            yield fake, app
    finally:
        await fake.close()


async def client_of(app: App) -> CharCountingClient:
    port: int = app.transports[0].port  # type: ignore[attr-defined]
    return await CharCountingClient.connect("127.0.0.1", port)


async def test_a_silent_controller_gets_ctrl_x_and_its_buffer_and_settings_are_adopted(
        tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        assert fake.resets == 1 and fake.lines[:5] == ["<reset>", "$I", "$$", "$#", "$G"]
        await wait_for(lambda: machine.controller.link.buffer_bytes == 255, 2.0, "Bf: 255")
        axes = list(app.kernel.config.core.axes.values())
        assert [a.steps_per_mm for a in axes] == [160, 160]
        assert [a.max_rate_mm_s for a in axes] == [100, 100]
        assert [a.accel_mm_s2 for a in axes] == [500, 500]
        assert [a.max_mm - a.min_mm for a in axes] == [200, 150]
        assert app.kernel.config.core.planner.junction_deviation_mm == 0.02
        assert not app.kernel.config.core.machine.soft_limits, "the board has no $20=1"
        client = await client_of(app)
        try:  # no soft limits on the board: motiond checks none either
            assert (await client.command("G0 Y160"))[-1] == "ok"
        finally:
            await client.close()


async def test_the_controllers_g92_stored_positions_and_tool_offset_are_adopted(
        tmp_path: Path) -> None:
    """Offsets set on the board before motiond connected: motiond's work positions and soft
    limits must use them, as the board does with the lines motiond sends."""
    board = ("[G54:10.000,5.000]", "[G28:1.000,2.000]", "[G30:3.000,99999999999.000]",
             "[G92:20.000,-5.000]", "[TLO:1.500]", "[PRB:0.000,0.000:0]")
    async with linked(tmp_path, offsets=board) as (fake, app):
        interpreter = app.kernel.machine.interpreter
        report = interpreter.offsets_report()
        assert report[:4] == ["[G54:10.000,5.000]", "[G55:0.000,0.000]", "[G56:0.000,0.000]",
                              "[G57:0.000,0.000]"]
        assert report[6:10] == ["[G28:1.000,2.000]", "[G30:0.000,0.000]",  # out of range
                                "[G92:20.000,-5.000]", "[TLO:1.500]"]
        assert interpreter.wco() == (30.0, 0.0), "G54 + G92 (no Z for the tool offset)"


async def test_an_unknown_controller_error_is_error_20_with_its_number(tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            result = await client.stream(["G0 X1", "M100", "G0 X3", "G0 X2"])
        finally:
            await client.close()
        # M100 is motiond's own refusal (never sent); G0X3 the board's, with its number
        assert result.replies == ["ok", "error:20", "error:20", "ok"]
        assert "[MSG:controller error:79 on G0X3]" in result.messages
        assert fake.lines[-3:] == ["G0X1", "G0X3", "G0X2"]


async def test_a_controller_that_restarts_by_itself_alarms(tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            fake.restart()
            await wait_for(lambda: app.kernel.state is MachineState.ALARM, 2.0, "the alarm")
            assert app.kernel.alarm_code == 42
            assert (await client.command("G0 X1"))[-1] == "error:9"
            assert (await client.command("$X"))[-1] == "ok"
            assert (await client.command("G0 X1"))[-1] == "ok"
        finally:
            await client.close()


async def test_a_board_that_does_not_come_back_from_ctrl_x_is_reconnected(
        tmp_path: Path) -> None:
    async with linked(tmp_path, reply_timeout_s=0.5) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await client_of(app)
        try:
            fake.mute_next_reset = True
            client.writer.write(b"\x18")
            while (await client._line(5.0)) != MOTIOND_BANNER:  # motiond's, to its client
                pass
            # this line waits for the board's banner, which never comes: refused, not hung
            assert (await client.command("G0 X1", timeout_s=5.0))[-1] == "error:45"
            await wait_for(lambda: app.kernel.alarm_code == 42, 2.0, "ALARM:42")
            await wait_for(lambda: fake.connections == 2 and machine.controller.ready, 5.0,
                           "the reconnection")
            assert (await client.command("$X"))[-1] == "ok"
            assert (await client.command("G0 X1"))[-1] == "ok"
        finally:
            await client.close()


async def test_replies_wait_in_order_behind_an_unanswered_line_and_are_bounded(
        tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            fake.holding = True
            client.writer.write(b"G0 X5\n" + b"$G\n" * 150)  # streamed without counting
            await wait_for(lambda: "G0X5" in fake.lines, 2.0, "the line at the board")
            await asyncio.sleep(0.2)
            (session,) = _sessions(app)
            # replies queued, up to the bound ($G goes to the board too: its buffer holds
            # the rest back)
            assert 30 <= len(session._replies) <= INBOUND_LINES
            fake.release()
            replies = [await client._line(5.0) for _ in range(1 + 2 * 150)]
        finally:
            await client.close()
        assert replies[0] == "ok", "the board's answer comes first, in order"
        assert replies[1::2] == [replies[1]] * 150 and replies[1].startswith("[GC:")
        assert replies[2::2] == ["ok"] * 150


def _sessions(app: App) -> list[Session]:
    transport = app.transports[0]
    return [session for _, session in transport._clients.values()]  # type: ignore[attr-defined]


async def test_a_line_waiting_for_room_when_another_client_resets_is_not_sent_late(
        tmp_path: Path) -> None:
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        streamer, other = await client_of(app), await client_of(app)
        lines = [f"G0 X{n}" for n in range(10, 90)]  # 6 bytes each on the wire: 42 fit in 255
        await wait_for(lambda: machine.controller.link.buffer_bytes == 255, 2.0, "Bf: confirmed")
        try:
            fake.holding = True
            streamer.writer.write("".join(f"{line}\n" for line in lines).encode())
            await wait_for(lambda: machine.controller.link.in_flight == 42, 2.0, "a full window")
            other.writer.write(b"\x18")
            heard: list[str] = []
            while MOTIOND_BANNER not in heard:
                heard.append(await streamer._line(5.0))
        finally:
            await streamer.close()
            await other.close()
        reset_at = len(fake.lines) - 1 - fake.lines[::-1].index("<reset>")  # the last one
        assert fake.lines[reset_at - 42:reset_at] == [line.replace(" ", "") for line in lines[:42]]
        after = fake.lines[reset_at + 1:]
        assert "G0X52" not in after, "the line that waited for room was sent after the reset"
        assert not [line for line in heard if line == "ok" or line.startswith("error")], (
            "as Grbl after a reset, the lines it dropped get no reply: the banner says so")


async def test_stopping_motiond_mid_job_resets_the_board_so_its_tools_go_off(
    tmp_path: Path,
) -> None:
    """Shutdown turns the tools off at once: the board gets Ctrl-X (Grbl stops motion and turns
    the spindle and laser off) before motiond lets go of the connection."""
    async with linked(tmp_path) as (fake, app):
        client = await client_of(app)
        try:
            fake.holding = True  # the board's planner is full: the job is running
            client.writer.write(b"M3 S1000\nG1 X50 F600\n")
            await wait_for(lambda: "G1X50F600" in fake.lines, 2.0, "the job on the board")
            resets = fake.resets
            app.request_stop()
            await wait_for(lambda: fake.resets > resets, 2.0, "Ctrl-X at shutdown")
            assert fake.lines[-1] == "<reset>"
        finally:
            await client.close()


async def test_a_hold_the_board_did_not_take_is_sent_again_and_only_then(
        tmp_path: Path) -> None:
    """The board reports Run after ``!`` (it dropped it): motiond sends ``!`` again after the
    second poll still says so, and no more once it holds; after ``~`` a report of Run is
    what was asked."""
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        fake.report = b"<Run|MPos:1.000,0.000|Bf:14,255|FS:600,0>\r\n"
        client = await client_of(app)
        try:
            client.writer.write(b"!")
            await wait_for(lambda: fake.realtime == b"!!", 2.0, "the hold sent again")
            polls = machine.controller.status_polls
            fake.report = b"<Hold:0|MPos:1.000,0.000|Bf:14,255|FS:0,0>\r\n"
            await wait_for(lambda: machine.controller.status_polls >= polls + 4, 2.0, "polls")
            client.writer.write(b"~")
            fake.report = b"<Run|MPos:1.000,0.000|Bf:14,255|FS:600,0>\r\n"
            polls = machine.controller.status_polls
            await wait_for(lambda: machine.controller.status_polls >= polls + 6, 2.0, "polls")
        finally:
            await client.close()
    assert fake.realtime == b"!!~"


async def test_m290_is_sent_once_the_lines_before_are_answered_and_a_refusal_undoes_it(
        tmp_path: Path) -> None:
    """M290's lines are computed from motiond's state, the board's once every line before it
    is answered; the board refusing the first (its move) refuses the M290: nothing more is
    sent and motiond's interpreter is as before it."""
    async with linked(tmp_path) as (fake, app):
        machine = app.kernel.machine
        assert isinstance(machine, GrblMachine)
        client = await client_of(app)
        try:
            fake.holding = True
            fake.refused = {"G53G0X5.5": 9}
            client.writer.write(b"G0 X5\nM290 X0.5\n")
            await wait_for(lambda: "G0X5" in fake.lines, 2.0, "the line at the board")
            await asyncio.sleep(0.2)
            assert fake.lines[-1] == "G0X5", "M290 waits for the answer to the line before"
            before = machine.interpreter.save()
            fake.release()
            replies = [await client._line(5.0) for _ in range(3)]
        finally:
            await client.close()
        assert [text for text in replies if not text.startswith("[MSG:")] == ["ok", "error:9"]
        assert "[MSG:controller error:9 on G53G0X5.5]" in replies
        assert fake.lines[-1] == "G53G0X5.5", "no G92 after the refused move"
        assert machine.interpreter.save() == before and machine.interpreter.wco() == (0.0, 0.0)
        assert machine.lines_undone == 1
