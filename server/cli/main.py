"""``motiond``: serve (default), check-config, estimate, render, fleet."""

from __future__ import annotations

import argparse
import asyncio
import logging
import logging.handlers
import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from server import __version__
from server.config import Config
from server.config_loader import config_layers, load_config
from server.errors import ConfigError
from server.paths import find_config
from server.runtime import realtime

if TYPE_CHECKING:
    from server.app import App
    from server.runtime.sdnotify import Notifier

log = logging.getLogger("motiond")
LOOPS = ("auto", "uvloop", "asyncio")
LoopFactory = Callable[[], asyncio.AbstractEventLoop]

EPILOG = """\
examples:
  motiond                              serve the embedded default (a simulated laser cutter)
  motiond --config examples/cnc.toml   serve another machine
  motiond --pty /tmp/motiond           also serve a pseudo-terminal for serial-only senders
  motiond check-config my.toml         list every problem in a config file
  motiond estimate job.nc              job time, distances, size and whether it fits
  motiond estimate job.nc --origin 200,150 --require-fit
                                       ... placed with its work origin at X200 Y150 (machine
                                       mm); exit status 3 when it does not fit the travel
  motiond render job.nc -o job.svg     a picture of the toolpath coloured by speed
  motiond fleet --url mqtt://broker    every machine on an MQTT broker ([mqtt] module)
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="motiond",
        description="A networked motion controller speaking Grbl 1.1 and "
        "Smoothieware over TCP, WebSocket and serial.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"motiond {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    serve = commands.add_parser("serve", help="run the server (the default command)")
    _serve_options(serve, after_command=True)
    _serve_options(parser)
    health = commands.add_parser(
        "health", help="exit 0 when the server this config describes answers GET /health")
    _serve_options(health, after_command=True)
    check = commands.add_parser("check-config", help="validate a config file")
    check.add_argument("file", type=Path)
    for name, help_text in (
        ("estimate", "estimate a job's time and extent"),
        ("render", "draw a job's toolpath as SVG or PNG"),
    ):
        sub = commands.add_parser(name, help=help_text)
        sub.add_argument("file", type=Path, help="a G-code file")
        sub.add_argument(  # before or after the command (SUPPRESS keeps the one given first)
            "--config", type=Path, default=argparse.SUPPRESS,
            help="machine config (default: $MOTIOND_CONFIG, else embedded)")
        sub.add_argument(
            "--origin", type=_origin, metavar="X,Y[,Z]",
            help="the work origin in machine mm, where the tool starts (default: 0,0,0)")
        sub.add_argument(
            "--require-fit", action="store_true",
            help="exit with status 3 when the job does not fit the travel from the origin")
        sub.add_argument(
            "--no-limits",
            action="store_true",
            help="never fail for the travel (--require-fit is ignored); the time never "
            "depends on it",
        )
        if name == "estimate":
            sub.add_argument("--json", action="store_true", help="print JSON")
            sub.add_argument("--no-progress", action="store_true", help="no progress bar")
        else:
            sub.add_argument(
                "-o", "--output", type=Path, required=True, help="output file (.svg or .png)"
            )
            sub.add_argument("--power", action="store_true",
                             help="grey by laser power (S) instead of colour by speed")
    _import_options(commands)
    _fleet_options(commands)
    from server.service import add_parser as add_service_parser

    add_service_parser(commands)
    return parser


def _import_options(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sub = commands.add_parser(
        "import", help="make a laser job from a drawing (SVG, DXF, PNG, JPEG)",
        description="A drawing into G-code: one layer per colour (and per image), each cut "
        "as a line, filled, or engraved. Needs the [cam] extra.")
    sub.add_argument("file", type=Path, help="an .svg, .dxf, .png or .jpg file")
    sub.add_argument("-o", "--output", type=Path, required=True, help="the G-code file")
    sub.add_argument(
        "--layer", action="append", default=[], metavar="NAME:key=value,...",
        help="a layer's settings (repeatable): NAME a colour (#ff0000) or 'image'; keys "
        "mode=line|fill|image, speed (mm/min), power and min_power (%%), passes, interval "
        "(mm), angle (deg), overscan (mm), bidirectional, dither=grayscale|threshold|"
        "floyd-steinberg|jarvis|stucki, enabled")
    sub.add_argument("--order", metavar="NAME,NAME,...",
                     help="layers cut first, in this order (default: engravings, then cuts "
                     "from the innermost)")
    sub.add_argument("--material", metavar="NAME",
                     help="layer settings from the machine's material library, before --layer")
    sub.add_argument("--width-mm", type=float, help="an image's width (default: from its DPI)")
    sub.add_argument("--dpi", type=float, help="an image's resolution (default: its own, "
                     "else 96)")
    sub.add_argument("--json", action="store_true", help="print the layers as JSON")
    sub.add_argument("--config", type=Path, default=argparse.SUPPRESS,
                     help="machine config, for the laser's maximum S (default: embedded)")


FLEET_EPILOG = """\
Lists the machines whose [mqtt] module publishes under PREFIX/<machine>/ (the default
topic_prefix is motiond/<machine slug>), from their retained availability and status topics.

examples:
  motiond fleet --url mqtt://broker.local
  motiond fleet --url mqtts://broker.example.com --username ops --password-file ~/.mqtt-pw
  motiond fleet --url mqtt://127.0.0.1:1883 --json | jq '.[] | select(.state == "Alarm")'
"""


def _fleet_options(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    fleet = commands.add_parser(
        "fleet", help="list the machines on an MQTT broker with their state and job progress",
        description="Every motiond on an MQTT broker: online or offline, state, job, progress.",
        epilog=FLEET_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    fleet.add_argument(
        "--url", default=os.environ.get("MOTIOND_MQTT_URL", "mqtt://127.0.0.1:1883"),
        help="broker, mqtt://host[:1883] or mqtts://host[:8883] "
        "(default: $MOTIOND_MQTT_URL, else mqtt://127.0.0.1:1883)")
    fleet.add_argument("--prefix", default="motiond",
                       help="topic level above each machine's (default: motiond)")
    fleet.add_argument("--username", help="broker user")
    fleet.add_argument("--password-file", type=Path, help="file holding the broker password")
    fleet.add_argument("--ca-file", type=Path, help="mqtts: CA certificates to trust")
    fleet.add_argument("--wait-s", type=float, default=1.0,
                       help="how long to collect retained messages (default: 1.0)")
    fleet.add_argument("--json", action="store_true", help="print JSON, one object per machine")


def _origin(text: str) -> tuple[float, ...]:
    """``X,Y[,Z]`` in mm."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        values = ()
    if not 2 <= len(values) <= 3 or not all(abs(v) < 1e6 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give X,Y or X,Y,Z in mm")
    return values


def _serve_options(parser: argparse.ArgumentParser, *, after_command: bool = False) -> None:
    """The server's options; ``after_command``: for ``serve``'s own parser, whose defaults
    must not undo an option given before the command (``motiond --config X serve``)."""
    parser.add_argument(
        "--config",
        type=Path,
        default=_env_path("MOTIOND_CONFIG"),
        help="machine config file (default: $MOTIOND_CONFIG, else motiond.toml in ./, "
        "~/.config/motiond or /etc/motiond, else embedded)",
    )
    parser.add_argument("--host", help="bind address for TCP and HTTP (overrides config)")
    parser.add_argument("--tcp-port", type=int, help="raw TCP port (default 2323)")
    parser.add_argument("--http-port", type=int, default=_env_port("MOTIOND_HTTP_PORT"),
                        help="HTTP/WebSocket port (default: $MOTIOND_HTTP_PORT, else 8080)")
    parser.add_argument("--serial", metavar="DEVICE", help="also serve a serial device")
    parser.add_argument("--pty", metavar="PATH", help="also serve a pseudo-terminal linked at PATH")
    parser.add_argument(
        "--loop",
        choices=LOOPS,
        default="auto",
        help="event loop: asyncio's when its thread may run at real-time priority, else "
        "uvloop's when installed (pip install 'motiond[fast]'), else asyncio's (default: auto)",
    )
    parser.add_argument(
        "--log-level",
        default="info",
        choices=["debug", "info", "warning", "error"],
        help="default: info",
    )
    parser.add_argument(
        "--log-file", type=Path, default=_env_path("MOTIOND_LOG_FILE"),
        help="also log to this file, reopened when logrotate moves it (default: "
        "$MOTIOND_LOG_FILE, else stderr only)")
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=_env_path("MOTIOND_DATA_DIR"),
        help="data folder: job files in jobs/, settings (default: $MOTIOND_DATA_DIR, else "
        "[jobs] data_dir, else the user's data folder)",
    )
    if after_command:
        for action in parser._actions:  # noqa: SLF001 - argparse has no public way
            if action.dest != "help":
                action.default = argparse.SUPPRESS


def _env_port(name: str) -> int | None:
    value = os.environ.get(name)
    return _port(value) if value else None


def _port(text: str) -> int:
    if not text.isdecimal() or not 0 <= int(text) <= 65535:
        raise SystemExit(f"motiond: {text!r} is not a port (0-65535)")
    return int(text)


def _env_path(name: str) -> Path | None:
    value = os.environ.get(name)
    return Path(value) if value else None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        setup_logging(args.log_level, args.log_file)
    except OSError as exc:
        print(f"motiond: cannot open the log file {args.log_file}: {exc.strerror}",
              file=sys.stderr)
        return 2
    try:
        if args.command == "check-config":
            return check_config(args.file)
        if args.command == "fleet":
            from modules.mqtt.fleet import fleet_command

            return fleet_command(args)
        if args.command == "install-service":
            from server.service import install_service

            return install_service(args)
        config = _env_data_dir(load_config(args.config or find_config()))
        if args.command == "health":
            from server.health import check, health_url

            core = apply_overrides(args, config).core
            return check(health_url(None, core.http.port, core.http.host))
        if args.command == "estimate":
            from server.cli.offline import estimate_command

            return estimate_command(args, config)
        if args.command == "import":
            from server.cli.drawing import import_command

            return import_command(args, config)
        if args.command == "render":
            from server.cli.offline import render_command

            return render_command(args, config)
        return serve(args, config)
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print("motiond: refusing to start with an invalid config", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0


def setup_logging(level: str, log_file: Path | None) -> None:
    """Log to stderr and, with ``--log-file``, to a file as well."""
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if log_file is not None:
        log_file = log_file.expanduser()
        log_file.parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.handlers.WatchedFileHandler(log_file))
    logging.basicConfig(
        level=level.upper(), format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        handlers=handlers, force=log_file is not None)


def check_config(path: Path) -> int:
    from server.cli.config_view import describe, trusted
    from server.cli.offline import machine_interpreter

    try:
        config = _env_data_dir(load_config(path))
        machine_interpreter(config)  # builds the modules: codes claimed twice are errors too
    except ConfigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print(f"{path}: {len(exc.problems)} problem(s)", file=sys.stderr)
        return 1
    axes = ", ".join(config.core.axis_names)
    modules = ", ".join(spec.section for spec in config.modules) or "none"
    layers = config_layers(path)
    base = "extends the built-in machine" if len(layers) > 1 else "a machine of its own"
    print(f"{path}: ok ({config.core.machine.name}; axes {axes}; modules {modules}; {base})")
    print(trusted(config))
    print(f"# the machine it describes, each value with where it came from ({path}, the "
          f"built-in machine, or the option's default):")
    print("\n".join(describe(config, layers)))
    return 0


def _env_data_dir(config: Config) -> Config:
    """``$MOTIOND_DATA_DIR`` for every command, unless the config names its data folder
    (``serve``'s ``--data-dir`` wins over both)."""
    folder = _env_path("MOTIOND_DATA_DIR")
    if folder is not None and config.core.jobs.data_dir is None:
        config.core.jobs.data_dir = folder
    return config


def apply_overrides(args: argparse.Namespace, config: Config) -> Config:
    """Command-line options win over the config file."""
    core = config.core
    if args.host:
        core.tcp.host = core.http.host = args.host
    if args.tcp_port is not None:
        core.tcp.port = args.tcp_port
    if args.http_port is not None:
        core.http.port = args.http_port
    if args.serial:
        core.serial.device = args.serial
    if args.pty:
        core.serial.pty = args.pty
    if args.data_dir:
        core.jobs.data_dir = args.data_dir
    hosts = os.environ.get("MOTIOND_ALLOWED_HOSTS", "").replace(",", " ").split()
    if hosts:
        core.http.also_allowed_hosts = [*core.http.also_allowed_hosts, *hosts]
    return config


def loop_factory(name: str = "auto", realtime_priority: int = 0) -> LoopFactory:
    """The event loop ``serve`` runs on: asyncio's with microsecond timers
    (:mod:`server.runtime.selector`) when asked for, or for ``auto`` when the loop may run at
    real-time priority; else uvloop's when installed (``auto``) or asked for. Asking for uvloop
    without it installed is a ConfigError."""
    from server.runtime.selector import asyncio_loop

    if name == "asyncio" or (name == "auto" and realtime.allowed(realtime_priority)):
        return asyncio_loop
    try:
        import uvloop
    except ImportError:
        if name == "uvloop":
            raise ConfigError(["uvloop is not installed: pip install 'motiond[fast]'"]) from None
        return asyncio_loop
    factory: LoopFactory = uvloop.new_event_loop
    return factory


def serve(args: argparse.Namespace, config: Config) -> int:
    config = apply_overrides(args, config)
    try:
        _no_open_door(config)
    except OSError as exc:
        print(f"motiond listens beyond this machine without a token and cannot store one: "
              f"{exc}; set [protocol] token and [http] token (or $MOTIOND_TOKEN), or listen on "
              f"127.0.0.1", file=sys.stderr)
        return 1
    factory = loop_factory(getattr(args, "loop", "auto"), config.core.stepgen.realtime_priority)
    try:
        with asyncio.Runner(loop_factory=factory) as runner:
            return runner.run(_serve(config))
    except ExceptionGroup as group:  # a port another program holds, a device that is gone
        refused, other = group.split(OSError)
        if other is not None or refused is None:
            raise
        for error in refused.exceptions:
            print(f"motiond cannot start: {error}", file=sys.stderr)
        return 1


def _no_open_door(config: Config) -> None:
    """A port open beyond loopback without a token gets the stored one: say so, with the
    token (as Jupyter prints its URL), once at every start."""
    from server.transports.access import close_open_door

    core = config.core
    path = close_open_door(core)
    if path is None:
        return
    token = core.protocol.token or core.http.token
    print(f"motiond listens beyond this machine without a token set: control needs the token "
          f"in {path}:\n    {token}\n"
          f"  senders: send $AUTH={token} first (or list their addresses in [protocol] "
          f"trusted_clients);\n"
          f"  web UI: http://<this machine>:{core.http.port}/?token={token}",
          file=sys.stderr, flush=True)


async def _serve(config: Config) -> int:
    from server.app import App, default_transports
    from server.runtime.sdnotify import Notifier

    loop = asyncio.get_running_loop()
    priority = realtime.claim_for(loop, config.core.stepgen.realtime_priority)
    app = App(config, transports=default_transports(config))
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, app.request_stop)
    log.info("motiond %s: %s (event loop: %s)", __version__, config.core.machine.name,
             type(loop).__module__.split(".")[0])
    log.info("the event loop's thread runs at %s", priority.detail)
    notifier = Notifier.from_environment()
    ready = asyncio.create_task(_tell_systemd_when_ready(app, notifier), name="sd-notify")
    try:
        await app.run()
    finally:
        ready.cancel()
        notifier.notify("STOPPING=1")
    log.info("stopped")
    return 0


async def _tell_systemd_when_ready(app: App, notifier: Notifier) -> None:
    await app.ready.wait()
    notifier.notify("READY=1", f"STATUS=serving {app.kernel.config.core.machine.name}")
