"""The machine configuration: the pydantic models of every core section.

One TOML file describes the machine. Core sections are ``[machine]``, ``[axes.X]``,
``[planner]``, ``[stepgen]``, ``[backend]``, ``[tcp]``, ``[http]``, ``[serial]``, ``[protocol]``
and ``[jobs]``; every other section configures a module (``[laser]``, ``[switch.fan]``) and is
validated by that module's own model. Unknown sections and keys are errors. Reading a file into
a :class:`Config`, and reporting every problem as ``FILE: [section] key: message``, is
:mod:`server.config_loader`.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

AXIS_LETTERS = "XYZABC"


class Strict(BaseModel):
    """Base of every config model: unknown keys are errors, values are checked on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class MachineSection(Strict):
    name: str = "motiond"
    soft_limits: bool = True
    laser_mode: bool = True
    hold_on_disconnect: bool = False
    report_inches: bool = False
    status_report_mask: int = Field(1, ge=0, le=3)
    homing: bool | None = Field(
        None, description="Grbl $22: $H and G28.2 run only when on; unset: on with [endstops]")


class AxisConfig(Strict):
    steps_per_mm: float = Field(gt=0, le=1_000_000)
    max_rate_mm_s: float = Field(gt=0)
    accel_mm_s2: float = Field(gt=0)
    min_mm: float = 0.0
    max_mm: float

    @model_validator(mode="after")
    def _travel_not_empty(self) -> AxisConfig:
        if self.max_mm <= self.min_mm:
            raise ValueError("max_mm must be greater than min_mm")
        return self


class PlannerConfig(Strict):
    junction_deviation_mm: float = Field(0.01, gt=0, le=10)
    arc_tolerance_mm: float = Field(0.002, gt=0, le=1)
    max_blocks: int = Field(4096, ge=2, le=1_000_000)
    max_planned_s: float = Field(0.5, gt=0, le=60)
    min_feed_mm_s: float = Field(0.01, gt=0)


class StepgenConfig(Strict):
    tick_hz: float = Field(1000.0, ge=10, le=100_000)
    # SCHED_FIFO priority of the event loop's thread under `motiond serve`; 0 = ordinary
    # (see server/runtime/realtime.py)
    realtime_priority: int = Field(10, ge=0, le=99)


MCU_PIN_PATTERN = r"^!?[A-Za-z][A-Za-z0-9_]*$"
KLIPPER_BAUD = 250_000  # Klipper's own default for a UART-connected MCU


class KlipperAxisPins(Strict):
    """``[backend.axes.x]``: one stepper driver on the Klipper MCU (``!`` inverts a pin)."""

    step_pin: str = Field(pattern=MCU_PIN_PATTERN, description="e.g. PB13")
    dir_pin: str = Field(pattern=MCU_PIN_PATTERN, description="e.g. !PB12")
    enable_pin: str | None = Field(None, pattern=MCU_PIN_PATTERN, description="e.g. !PB14")
    step_pulse_s: float = Field(2e-6, ge=0, le=1e-3, description="minimum step pulse width")


class KlipperOutput(Strict):
    """``[backend.outputs.NAME]``: an output modules set by NAME (``[laser] pin = NAME``)."""

    pin: str | None = Field(None, pattern=MCU_PIN_PATTERN,
                            description="the MCU pin (default: NAME itself); ! inverts")
    pwm: bool = Field(True, description="hardware PWM (config_pwm_out); false: on/off")
    cycle_time_s: float = Field(0.0001, gt=0, le=1, description="PWM period (1/frequency)")
    max_duration_s: float = Field(
        1.0, ge=0.1, le=5.0,
        description="the firmware's watchdog: an output left on this long without a refresh "
        "from motiond (motiond died, hung or lost the link) is switched off by the board")


class BackendConfig(Strict):
    kind: Literal["sim", "null", "grbl", "klipper"] = Field(
        "sim", description="sim: the simulated machine; null: nothing; grbl: a Grbl, grblHAL "
        "or FluidNC controller downstream (serial or tcp); klipper: an MCU running Klipper's "
        "firmware executes the step generator's schedule (serial)")
    trace_csv: Path | None = None
    history_samples: int = Field(100_000, ge=0)
    probe_at_mm: dict[str, float] = Field(default_factory=dict)
    serial: str | None = Field(
        None, min_length=1,
        description="grbl: the controller's serial device; klipper: the MCU's (or a pty)")
    tcp: str | None = Field(
        None, pattern=r"^[^\s:]+:\d{1,5}$",
        description="grbl: the controller's host:port (FluidNC, grblHAL over the network)")
    baud: int = Field(
        115200, ge=300, le=4_000_000,
        description="serial speed (default 115200 for grbl, 250000 for klipper; USB ignores it)")
    # -- grbl
    buffer_bytes: int | None = Field(
        None, ge=16, le=65536,
        description="grbl: the controller's receive buffer for character counting; default "
        "the Bf: figure it reports, else 127")
    status_hz: float = Field(
        10.0, ge=5, le=20, description="grbl: how often the controller is polled with '?'")
    banner_timeout_s: float = Field(
        3.0, gt=0, le=60,
        description="grbl: wait this long for the banner after opening the port (an Arduino "
        "resets on open), then send Ctrl-X and wait again")
    reply_timeout_s: float = Field(
        10.0, gt=0, le=600, description="grbl: a start-up query ($I, $$, $#, $G) unanswered "
        "this long means the controller is not answering: the connection is retried")
    reconnect_s: float = Field(
        0.5, gt=0, le=60, description="grbl: retry opening a lost controller this often")
    silent_timeout_s: float = Field(
        2.0, ge=0.2, le=60, description="grbl: a connected controller that answers neither "
        "'?' nor a line this long is not answering: ALARM:42, Ctrl-X (tools off), reconnect")
    # -- klipper
    lead_time_s: float = Field(
        0.3, ge=0.02, le=2.0,
        description="klipper: trajectory time t executes at MCU time t + lead (also the most "
        "a feed hold takes to start decelerating, and the host stall it survives)")
    max_error_s: float = Field(
        25e-6, ge=1e-6, le=1e-3, description="klipper: how early a step may be (compression)")
    response_timeout_s: float = Field(
        0.5, ge=0.05, le=10, description="klipper: an MCU silent this long is an alarm")
    restart_method: Literal["command", "arduino"] = Field(
        "command", description="klipper: how a shut-down MCU is restarted ($X, M999, or one "
        "found shut down): command sends the firmware's reset (USB and UART boards); arduino "
        "toggles DTR (a board whose firmware lacks reset falls back to it)")
    axes: dict[str, KlipperAxisPins] = Field(default_factory=dict)
    outputs: dict[str, KlipperOutput] = Field(default_factory=dict)

    @model_validator(mode="before")
    @classmethod
    def _baud_of_kind(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("kind") == "klipper" and "baud" not in data:
            return {**data, "baud": KLIPPER_BAUD}
        return data

    @model_validator(mode="after")
    def _one_link(self) -> BackendConfig:
        if self.kind == "grbl" and (self.serial is None) == (self.tcp is None):
            raise ValueError('kind = "grbl" needs exactly one of serial = "/dev/ttyUSB0" '
                             'or tcp = "host:23"')
        if self.kind == "klipper" and self.serial is None:
            raise ValueError('kind = "klipper" needs serial (the MCU\'s device path)')
        if self.kind == "klipper" and self.tcp is not None:
            raise ValueError('tcp is an option of kind = "grbl"; a Klipper MCU is on serial')
        if self.kind not in ("grbl", "klipper") and (
            self.serial is not None or self.tcp is not None
        ):
            raise ValueError('serial and tcp are options of kind = "grbl" or "klipper"')
        return self


class TcpConfig(Strict):
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(2323, ge=0, le=65535)
    max_connections: int = Field(16, ge=1)
    reserved_connections: int = Field(
        4, ge=0, description="with a token: slots only a connection that logs in may use")
    idle_timeout_s: float = Field(
        60.0, gt=0, le=86_400,
        description="close a connection not logged in (token set) or that never sent a byte, "
        "after this long without receiving a byte")
    login_timeout_s: float = Field(
        10.0, gt=0, le=3600, description="a connection in a reserved slot must log in this fast")


class HttpConfig(Strict):
    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(8080, ge=0, le=65535)
    allowed_origins: list[str] = Field(default_factory=list)
    allowed_hosts: list[str] | None = Field(
        None,
        min_length=1,
        description="names a request's Host (and a page's Origin) may carry; default: localhost"
        " names, the bound address and this machine's names; '*' allows any",
    )
    also_allowed_hosts: list[str] = Field(
        default_factory=list,
        description="names allowed besides allowed_hosts (or its default): a container's "
        "host's names, as $MOTIOND_ALLOWED_HOSTS gives them (nas.local,nas)")
    token: str | None = None
    max_connections: int = Field(
        32, ge=1, description="WebSocket connections (/ws and /api) that presented the token"
    )
    max_unauthenticated_connections: int = Field(
        8, ge=0, le=10_000, description="WebSocket connections without the token (when one is set)"
    )
    max_requests_per_s: float = Field(200.0, gt=0, description="per /api connection")
    ws_max_message_bytes: int = Field(
        64 << 10, ge=1024, le=16 << 20, description="largest /ws message, once decompressed"
    )
    api_max_message_bytes: int = Field(
        1 << 20, ge=4096, le=64 << 20, description="largest /api message, once decompressed"
    )
    unauthenticated_max_message_bytes: int = Field(
        16 << 10, ge=1024, le=64 << 20, description="largest /api message before the token"
    )
    idle_timeout_s: float = Field(
        300.0, gt=0, le=86_400, description="closes a socket without the token sending nothing"
    )
    request_timeout_s: float = Field(
        15.0, gt=0, le=3600, description="for a request's headers, and idle keep-alive"
    )
    max_pending_requests: int = Field(
        64, ge=1, le=10_000, description="connections that have not yet sent a whole first "
        "request; further ones are closed at once (half-sent requests cannot fill the "
        "descriptor table and lock the TCP operator out)")
    first_request_timeout_s: float = Field(
        5.0, gt=0, le=3600, description="a connection's first request must arrive whole "
        "this fast")


class SerialConfig(Strict):
    device: str | None = None
    baud: int = Field(115200, gt=0)
    pty: str | None = None
    pty_group: str = Field(
        "dialout",
        description="the pseudo-terminal's group, as a serial port's (a host such as OctoPrint "
        "running as its own user in that group can open it); empty: leave it as created")
    pty_mode: int = Field(
        0o660, ge=0, le=0o666,
        description="the pseudo-terminal's permissions (0o660: owner and group read and write)")


class ProtocolConfig(Strict):
    dialect: Literal["auto", "grbl", "reprap"] = "auto"
    line_limit: int = Field(256, ge=16, le=65536)
    rx_buffer_bytes: int = Field(128, ge=16, le=65536)
    outgoing_limit_bytes: int = Field(1 << 20, ge=1024)
    token: str | None = Field(None, min_length=8, description="also $MOTIOND_TOKEN")
    unauthenticated: Literal["read-only", "none"] = "read-only"
    backlog_bytes: int = Field(
        2 << 20, ge=4096, le=1 << 30,
        description="input held per connection while its line queue is full; realtime bytes "
        "in it are acted on at once; beyond it the transport stops reading")
    read_only_input_bytes_per_s: float = Field(
        2048.0, gt=0, le=1 << 30,
        description="what a connection that may not control (not logged in, an observer) may "
        "send: beyond it its bytes wait unread, realtime bytes included")
    read_only_input_total_bytes_per_s: float = Field(
        8192.0, gt=0, le=1 << 30,
        description="the same, all such connections together (their loop time stays bounded "
        "whatever their number)")
    realtime_bytes_per_s: float = Field(
        1024.0, gt=0, le=1 << 30,
        description="realtime bytes ('?', '!', '~', Ctrl-X, overrides) examined per connection, "
        "controlling ones too (senders send a few dozen a second): a flood beyond it waits "
        "unread")
    realtime_total_bytes_per_s: float = Field(
        4096.0, gt=0, le=1 << 30,
        description="the same, all flooding connections together; a connection within half its "
        "own budget (the operator's '!') never waits for them")
    trusted_clients: list[str] = Field(
        default_factory=list,
        description="addresses and subnets (192.168.1.0/24) that control without the token: "
        "for senders that cannot log in (LightBurn, most Grbl senders)")
    status_reports_per_s: float = Field(
        200.0, gt=0, le=1000,
        description="per connection (senders poll at 5-100 Hz); further '?' share the next report")
    auth_failures_per_connection: int = Field(
        3, ge=1, le=100, description="wrong $AUTH tokens before the connection is closed")
    auth_delay_s: float = Field(
        0.5, ge=0, le=10,
        description="a wrong token is answered this late, doubling with each recent failure "
        "from the same address")
    auth_max_delay_s: float = Field(8.0, ge=0, le=300, description="cap of that delay")

    @field_validator("trusted_clients")
    @classmethod
    def _networks(cls, entries: list[str]) -> list[str]:
        for entry in entries:
            client_network(entry)
        return entries


Network = ipaddress.IPv4Network | ipaddress.IPv6Network
_MAPPED = ipaddress.IPv6Network("::ffff:0:0/96")


def client_network(entry: str) -> Network:
    """One ``trusted_clients`` entry as a network (an address is a network of one; an
    IPv4-mapped IPv6 one is its IPv4 form, as clients' addresses are compared).

    Raises:
        ValueError: not an address or subnet, host bits set (``192.168.1.77/24``: which was
            meant?), or a ``/0`` (every address: no token at all).
    """
    text = entry.strip()
    try:
        network = ipaddress.ip_network(text, strict=False)
    except ValueError:
        raise ValueError(f"not an address or subnet: {entry!r}") from None
    if network.prefixlen == 0:
        raise ValueError(f"{entry!r} trusts every address, as if no token were set: list your "
                         "own computers (192.168.1.77) or their subnet (192.168.1.0/24)")
    if network.network_address != ipaddress.ip_interface(text).ip:
        raise ValueError(f"{entry!r} has host bits set: write {network} for the subnet or "
                         f"{text.split('/')[0]} for the one address")
    if isinstance(network, ipaddress.IPv6Network) and network.subnet_of(_MAPPED):
        mapped = network.network_address.ipv4_mapped
        return ipaddress.IPv4Network(f"{mapped}/{max(network.prefixlen - 96, 0)}")
    return network


def client_networks(entries: list[str]) -> list[Network]:
    """``[protocol] trusted_clients`` as networks."""
    return [client_network(entry) for entry in entries]


def trusted_client(address: str | None, entries: list[str]) -> bool:
    """Whether a client's address is in ``[protocol] trusted_clients``."""
    if not entries or not address:
        return False
    try:
        ip = ipaddress.ip_address(address.split("%")[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return any(ip in network for network in client_networks(entries))


class JobsConfig(Strict):
    data_dir: Path | None = Field(
        None, description="motiond's data folder (job files in jobs/, the default machine's "
        "settings.toml); default: the user's data folder, see server/paths.py")
    jobs_dir: Path | None = Field(
        None, description="the job files' folder; default: jobs/ in the data folder. "
        "Moonraker's gcodes folder when Moonraker runs in front ([klippy_api])")
    max_upload_bytes: int = Field(256 << 20, gt=0)
    frame_feed_mm_min: float = Field(3000.0, gt=0)  # Frame: the speed round the job's extent
    frame_power_s: float = Field(0.0, ge=0)  # Frame: 0 = laser off (jogs); else M3 at this S


class CoreConfig(Strict):
    machine: MachineSection = Field(default_factory=MachineSection)
    axes: dict[str, AxisConfig]
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    stepgen: StepgenConfig = Field(default_factory=StepgenConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    tcp: TcpConfig = Field(default_factory=TcpConfig)
    http: HttpConfig = Field(default_factory=HttpConfig)
    serial: SerialConfig = Field(default_factory=SerialConfig)
    protocol: ProtocolConfig = Field(default_factory=ProtocolConfig)
    jobs: JobsConfig = Field(default_factory=JobsConfig)

    @model_validator(mode="after")
    def _axis_letters(self) -> CoreConfig:
        bad = [name for name in self.axes if name.upper() not in AXIS_LETTERS]
        if bad:
            raise ValueError(f"axis names must be among {', '.join(AXIS_LETTERS)}, not {bad}")
        if len({name.upper() for name in self.axes}) != len(self.axes):
            raise ValueError("an axis is named twice")
        if self.backend.kind == "klipper":
            pins = {name.upper() for name in self.backend.axes}
            missing = [name for name in self.axes if name.upper() not in pins]
            if missing or len(pins) != len(self.axes):
                raise ValueError(f"[backend.axes.*] must give the pins of every axis "
                                 f"({', '.join(self.axis_names)}); missing {missing}")
        return self

    @model_validator(mode="after")
    def _controller_not_served(self) -> CoreConfig:
        device = self.backend.serial
        if device is not None and device in (self.serial.device, self.serial.pty):
            raise ValueError(f"{device} is the Grbl controller's ([backend] serial): it cannot "
                             "also be served to senders ([serial] device or pty)")
        return self

    @property
    def axis_names(self) -> tuple[str, ...]:
        """Axis letters, upper-case, in configuration order."""
        return tuple(name.upper() for name in self.axes)


class ModuleClass(Protocol):
    """What the configuration knows of a module class (:class:`server.kernel.module.Module`
    is one): it is built from its context and its validated section."""

    def __call__(self, ctx: Any, config: Any, /) -> Any: ...


@dataclass(frozen=True, slots=True)
class ModuleSpec:
    """One configured module instance: ``[laser]`` or ``[switch.fan]``."""

    cls: ModuleClass
    section: str  # "laser" or "switch.fan"
    instance: str | None  # "fan" for named instances
    config: BaseModel


@dataclass(frozen=True, slots=True)
class Config:
    core: CoreConfig
    modules: tuple[ModuleSpec, ...]
    path: Path | None = None

    def laser_max_s(self) -> float:
        """The configured laser's S for full power (Grbl's $30; 1000 without a [laser]):
        what an imported drawing's power in percent is scaled to."""
        for spec in self.modules:
            if spec.section == "laser":
                return float(getattr(spec.config, "maximum_s_value", 1000.0))
        return 1000.0

