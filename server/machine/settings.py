"""Grbl's numbered settings (``$$``, ``$x=value``), mapped onto the live machine.

Each number reads and writes one value of the running configuration; a write is validated by
the same pydantic model as the config file, applied at once where that is safe (junction
deviation, arc tolerance, rates, accelerations, soft limits, report units) and persisted to
a small TOML settings file next to the config, which is read again at start-up. Settings that
change the machine's geometry (steps/mm, travel), and ``$RST=$``, are refused while motion is
queued (error 8).

Values are checked as Grbl does, in its order: a value that is not a plain finite number is
error 2 (bad number format), a negative one error 4, an unknown setting error 3, a fixed one
error 5; a value outside the setting's range (:attr:`Setting.low`..:attr:`Setting.high`) is
error 3. The settings file is replaced atomically (temporary file, fsync, rename, fsync of the
folder), so a crash while writing leaves the old or the new file, never an empty one; a file
that cannot be read or parsed is reported with a warning naming it, never silently ignored.
"""

from __future__ import annotations

import logging
import math
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from server.errors import CommandError, Error

if TYPE_CHECKING:
    from server.config import CoreConfig

log = logging.getLogger("motiond.settings")
MM_PER_MIN = 60.0
_VALUE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")  # Grbl's read_float: no exponent, inf or nan
# Ranges beyond the config models' own bounds (which still apply). The arc tolerance's floor
# keeps a circle of 1 m radius under 7,100 chords (0.1 µm, ten times finer than a 1000 steps/mm
# axis resolves); rates, accelerations and travels are bounded far above any real machine so
# that a typo like $110=1e30 cannot make a move last no time at all.
ARC_TOLERANCE_MIN_MM = 0.0001
MAX_RATE_MM_MIN = 1_000_000.0
MAX_ACCEL_MM_S2 = 1_000_000.0
MAX_TRAVEL_MM = 1_000_000.0


@dataclass(frozen=True, slots=True)
class Setting:
    """One numbered setting: how to read it from and write it to the config."""

    number: int
    description: str
    read: Callable[[CoreConfig], float]
    write: Callable[[CoreConfig, float], None] | None = None
    geometry: bool = False  # changes steps or travel: only while idle
    low: float = 0.0  # inclusive bounds; the config model may exclude 0 itself
    high: float = math.inf


def _fixed(value: float, description: str) -> Callable[[int], Setting]:
    return lambda number: Setting(number, description, lambda core: value)


Accessors = tuple[Callable[..., float], Callable[..., None]]


def _attr(section: str, key: str, scale: float = 1.0) -> Accessors:
    def read(core: CoreConfig) -> float:
        return float(getattr(getattr(core, section), key)) * scale

    def write(core: CoreConfig, value: float) -> None:
        setattr(getattr(core, section), key, value / scale)

    return read, write


def _axis(index: int, key: str, scale: float = 1.0) -> Accessors:
    def read(core: CoreConfig) -> float:
        return float(getattr(list(core.axes.values())[index], key)) * scale

    def write(core: CoreConfig, value: float) -> None:
        setattr(list(core.axes.values())[index], key, value / scale)

    return read, write


def setting_table(core: CoreConfig) -> dict[int, Setting]:
    """Every setting this machine has, by number."""
    table: dict[int, Setting] = {}
    for number, value, text in (
        (0, 10, "step pulse, µs"),
        (1, 25, "step idle delay, ms"),
        (2, 0, "step pulse invert"),
        (3, 0, "direction invert"),
        (4, 0, "step enable invert"),
        (5, 0, "limit pins invert"),
        (6, 0, "probe pin invert"),
        (21, 0, "hard limits"),
        (30, 1000, "max spindle/laser S"),
        (31, 0, "min spindle/laser S"),
    ):
        table[number] = _fixed(value, text)(number)
    table[10] = Setting(10, "status report mask", *_attr("machine", "status_report_mask"))
    table[11] = Setting(11, "junction deviation, mm", *_attr("planner", "junction_deviation_mm"))
    table[12] = Setting(
        12, "arc tolerance, mm", *_attr("planner", "arc_tolerance_mm"), low=ARC_TOLERANCE_MIN_MM
    )
    table[13] = Setting(13, "report inches", *_bool("machine", "report_inches"))
    table[20] = Setting(20, "soft limits", *_bool("machine", "soft_limits"))
    table[22] = Setting(22, "homing cycle", *_bool("machine", "homing"))
    for homing, (default, about, high) in HOMING_SETTINGS.items():
        table[homing] = _stored(homing, default, about, high)
    table[32] = Setting(32, "laser mode", *_bool("machine", "laser_mode"))
    for index, _ in enumerate(core.axes):
        _axis_settings(table, index)
    return table


def _axis_settings(table: dict[int, Setting], index: int) -> None:
    table[100 + index] = Setting(
        100 + index, "steps/mm", *_axis(index, "steps_per_mm"), geometry=True
    )
    table[110 + index] = Setting(
        110 + index,
        "max rate, mm/min",
        *_axis(index, "max_rate_mm_s", MM_PER_MIN),
        high=MAX_RATE_MM_MIN,
    )
    table[120 + index] = Setting(
        120 + index, "acceleration, mm/s^2", *_axis(index, "accel_mm_s2"), high=MAX_ACCEL_MM_S2
    )
    table[130 + index] = Setting(
        130 + index, "max travel, mm", *_travel(index), geometry=True, high=MAX_TRAVEL_MM
    )


def _bool(section: str, key: str) -> Accessors:
    def read(core: CoreConfig) -> float:
        return float(bool(getattr(getattr(core, section), key)))

    def write(core: CoreConfig, value: float) -> None:
        setattr(getattr(core, section), key, bool(value))

    return read, write


def _travel(index: int) -> Accessors:
    def read(core: CoreConfig) -> float:
        axis = list(core.axes.values())[index]
        return axis.max_mm - axis.min_mm

    def write(core: CoreConfig, value: float) -> None:
        axis = list(core.axes.values())[index]
        if axis.min_mm < 0 and axis.max_mm <= 0:  # negative machine space (Grbl style)
            axis.min_mm = axis.max_mm - value
        else:
            axis.max_mm = axis.min_mm + value

    return read, write


def _stored(number: int, value: float, description: str, high: float) -> Setting:
    """A setting kept for a part that is not configured (Grbl's homing settings without an
    ``[endstops]`` section): listed and written as Grbl's, acting on nothing until a module
    adopts it (:meth:`Settings.adopt`), which then takes the value."""
    cell = [value]

    def write(core: CoreConfig, new: float) -> None:
        cell[0] = new

    return Setting(number, description, lambda core: cell[0], write, high=high)


# Grbl 1.1h's homing settings, with its defaults (defaults.h), until a module adopts them:
# $23 direction invert mask, $24 locate feed mm/min, $25 seek rate mm/min, $26 debounce ms,
# $27 pull-off mm.
HOMING_SETTINGS: dict[int, tuple[float, str, float]] = {
    23: (0, "homing direction invert mask", 255),
    24: (25.0, "homing locate feed, mm/min", MAX_RATE_MM_MIN),
    25: (500.0, "homing seek rate, mm/min", MAX_RATE_MM_MIN),
    26: (250, "homing debounce, ms", 65535),
    27: (1.0, "homing pull-off, mm", MAX_TRAVEL_MM),
}
FLOAT_SETTINGS = frozenset({11, 12, 24, 25, 27})


def _typed(number: int, value: float) -> float | int:
    return value if number >= 100 or number in FLOAT_SETTINGS else int(value)


class Settings:
    """The numbered settings of one machine, with persistence."""

    def __init__(
        self,
        core: CoreConfig,
        path: Path | None,
        *,
        is_idle: Callable[[], bool],
        apply: Callable[[], None],
    ) -> None:
        """``core`` is changed in place; ``apply`` pushes it into the motion pipeline;
        ``is_idle`` says whether motion is queued (geometry changes wait for idle)."""
        self.core = core
        self._is_idle, self._apply = is_idle, apply
        self.table = setting_table(self.core)
        self._adopted: dict[int, float] = {}  # a module's settings: their config's values
        self.path = path
        self._config_values = {  # what the config says: only changes from it are saved
            number: setting.read(core) for number, setting in self.table.items()
        }
        if path is not None and path.exists():
            self._load(path)

    def adopt(self, setting: Setting) -> None:
        """A module's own setting in place of the stored one of that number (``$23``-``$27``:
        the homing module's); a value saved or written before it was adopted carries over."""
        number = setting.number
        stored = self.table[number].read(self.core)
        self._config_values[number] = setting.read(self.core)
        self._adopted[number] = setting.read(self.core)
        self.table[number] = setting
        if stored != HOMING_SETTINGS.get(number, (stored,))[0]:
            try:
                self.set(number, stored)
            except CommandError as exc:
                log.warning("$%d: kept %g, not the saved %g: %s", number,
                            self._config_values[number], stored, exc)

    def values(self) -> dict[int, float | int]:
        """Every setting's value; integer and on/off settings as ints (``$10=1``, not ``1.000``)."""
        return {
            number: _typed(number, setting.read(self.core))
            for number, setting in sorted(self.table.items())
        }

    def write(self, statement: str) -> None:
        """Apply ``N=value`` (the text after ``$``) live; raise CommandError with Grbl's codes.
        Persisting it is :meth:`save` of :meth:`file_text`, which blocks: call it in a thread."""
        number_text, equals, value_text = statement.partition("=")
        try:
            number = int(number_text.strip())
        except ValueError as exc:
            raise CommandError(Error.INVALID_STATEMENT, f"invalid statement ${statement}") from exc
        if not equals:
            raise CommandError(Error.INVALID_STATEMENT, f"invalid statement ${statement}")
        if _VALUE.fullmatch(value_text.strip()) is None:
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, f"${number}: bad number {value_text.strip()!r}"
            )
        self.set(number, float(value_text))

    def set(self, number: int, value: float) -> None:
        """Check ``value`` as Grbl does (see the module docstring), then apply it live."""
        setting = self._checked(number, value)
        if setting.write is None:
            return
        try:
            setting.write(self.core, int(value) if number == 10 else value)
        except ValidationError as exc:
            message = exc.errors()[0]["msg"]
            raise CommandError(Error.INVALID_STATEMENT, f"${number}: {message}") from exc
        self._apply()

    def _checked(self, number: int, value: float) -> Setting:
        if not math.isfinite(value):
            raise CommandError(
                Error.BAD_NUMBER_FORMAT, f"${number}: {value} is not a finite number"
            )
        if value < 0:
            raise CommandError(Error.NEGATIVE_VALUE, f"${number} must not be negative")
        setting = self.table.get(number)
        if setting is None:
            raise CommandError(Error.INVALID_STATEMENT, f"no setting ${number}")
        if setting.write is None:
            if value != setting.read(self.core):
                raise CommandError(
                    Error.SETTING_DISABLED, f"${number} ({setting.description}) is fixed"
                )
            return setting
        if not setting.low <= value <= setting.high:
            raise CommandError(
                Error.INVALID_STATEMENT,
                f"${number} ({setting.description}) must be between {setting.low:g} "
                f"and {setting.high:g}",
            )
        if setting.geometry and not self._is_idle():
            raise CommandError(Error.NOT_IDLE, f"${number} can only change while idle")
        return setting

    def restore_defaults(self, defaults: CoreConfig) -> None:
        """``$RST=$``: every writable setting back to the config file's value (only while idle:
        steps/mm and travel must not change under a moving machine)."""
        if not self._is_idle():
            raise CommandError(Error.NOT_IDLE, "$RST=$ can only run while idle")
        for number, setting in self.table.items():
            if setting.write is None:
                continue
            if number in self._adopted:
                setting.write(self.core, self._adopted[number])
            elif number in HOMING_SETTINGS:
                setting.write(self.core, HOMING_SETTINGS[number][0])
            else:
                setting.write(self.core, setting.read(defaults))
        self._apply()
        if self.path is not None and self.path.exists():
            self.path.unlink()

    def _load(self, path: Path) -> None:
        saved = _read_saved(path)
        if saved is None:
            return
        for key, value in saved.items():
            try:
                self.set(int(key), float(value))
            except (ValueError, TypeError, CommandError) as exc:
                log.warning("%s: ignored the saved value $%s = %r: %s", path, key, value, exc)

    def file_text(self) -> str:
        """The settings file's contents (taken on the loop): only the values now in force
        that differ from the config file's, so a default changed in the config still moves
        the settings nobody set, and a setting set back to the config's value is dropped."""
        lines = [
            "# Written by motiond for $x=value; delete to go back to the config file.",
            "[settings]",
        ]
        for number, setting in sorted(self.table.items()):
            value = setting.read(self.core)
            if setting.write is not None and value != self._config_values[number]:
                lines.append(f'"{number}" = {value!r}')
        return "\n".join(lines) + "\n"

    def save(self, text: str) -> None:
        """Write ``text`` (:meth:`file_text`) atomically; blocks for an fsync or two, so the
        server calls it in a thread. The ok of ``$x=`` comes once the value is on disk.

        Raises:
            OSError: not saved (a full disk, a read-only folder); the file is as it was.
        """
        if self.path is not None:
            write_atomically(self.path, text)

    def snapshot(self) -> dict[int, float]:
        """Every writable setting's value now, for :meth:`restore`."""
        return {number: setting.read(self.core) for number, setting in self.table.items()
                if setting.write is not None}

    def restore(self, values: dict[int, float]) -> None:
        """Put back a :meth:`snapshot` (a value that could not be saved is not kept)."""
        for number, value in values.items():
            write = self.table[number].write
            if write is not None and self.table[number].read(self.core) != value:
                write(self.core, value)
        self._apply()


def _read_saved(path: Path) -> dict[str, Any] | None:
    """The ``[settings]`` table of a settings file, or None (with a warning saying why)."""
    fallback = "the config file's values are used instead"
    try:
        text = path.read_text()
        data: dict[str, Any] = tomllib.loads(text)
    except OSError as exc:
        log.warning("%s: cannot read the saved settings (%s): %s", path, exc, fallback)
        return None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        log.warning("%s: the saved settings are not valid TOML (%s): %s", path, exc, fallback)
        return None
    saved = data.get("settings")
    if saved == {} and "[settings]" in text:  # every setting back at the config's value
        return None
    if not isinstance(saved, dict) or not saved:
        log.warning(
            "%s: no [settings] values in the saved settings (an empty or truncated file?): %s",
            path,
            fallback,
        )
        return None
    return saved


def write_atomically(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` so that a crash at any point leaves the old or the new
    file: write a temporary file in the same folder, fsync it, rename it over ``path``, then
    fsync the folder so the rename itself is durable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(path.name + ".tmp")
    try:
        with temp.open("w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temp, path)
    except BaseException:
        temp.unlink(missing_ok=True)  # a full disk leaves no half-written file behind
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
