"""Reading the machine configuration: TOML loading, module sections and readable errors.

:func:`load_config` reads a file (or the embedded default), :func:`build_config` validates a
parsed mapping against the core models (:mod:`server.config`) and each configured module's own
model. Every problem is reported as ``FILE: [section] key: message``; unknown sections and keys
are errors.
"""

from __future__ import annotations

import difflib
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from types import UnionType
from typing import Any, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError

from server.config import Config, CoreConfig, ModuleSpec
from server.errors import ConfigError
from server.kernel.module import Module, available_modules
from server.paths import check_config_file

CORE_SECTIONS = frozenset(CoreConfig.model_fields)
DEFAULT_LABEL = "<default config>"


def default_config_text() -> str:
    """The embedded default machine: a laser cutter on the simulated backend."""
    return resources.files("server").joinpath("default.toml").read_text()


def load_config(
    path: Path | None = None, registry: Mapping[str, type[Module]] | None = None
) -> Config:
    """Load and validate a config file (the embedded default when ``path`` is None): the
    built-in machine extended by the file (:func:`config_layers`)."""
    layers = config_layers(path)
    data: dict[str, Any] = {}
    for _, layer in layers:
        data = extend(data, layer)
    return build_config(data, str(path) if path else DEFAULT_LABEL, registry, path)


def config_layers(path: Path | None) -> list[tuple[str, dict[str, Any]]]:
    """The parsed tables a config is made of, each with its label, later ones winning: the
    built-in machine, then the file. A file that names ``[axes]`` describes a machine of its
    own and stands alone (it would otherwise inherit the built-in Z axis, laser and
    endstops); any other file extends the built-in machine, so ``[protocol] trusted_clients
    = [...]`` alone is a whole config."""
    default = (DEFAULT_LABEL, _parse(default_config_text(), DEFAULT_LABEL))
    if path is None:
        return [default]
    check_config_file(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError([f"{path}: cannot read: {exc.strerror}"]) from exc
    own = (str(path), _parse(text, str(path)))
    return [own] if "axes" in own[1] else [default, own]


def extend(base: Mapping[str, Any], own: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with every table and key ``own`` names replaced, tables merged key by key."""
    merged = dict(base)
    for key, value in own.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = extend(merged[key], value)
        else:
            merged[key] = value
    return merged


def _parse(text: str, label: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"{label}: not valid TOML: {exc}"]) from exc


def build_config(
    data: Mapping[str, Any],
    label: str = "<config>",
    registry: Mapping[str, type[Module]] | None = None,
    path: Path | None = None,
) -> Config:
    """Validate a parsed config mapping; raise :class:`ConfigError` listing every problem."""
    modules_available = available_modules() if registry is None else registry
    core_data = {key: value for key, value in data.items() if key in CORE_SECTIONS}
    problems: list[str] = []
    core: CoreConfig | None = None
    try:
        core = CoreConfig.model_validate(core_data)
    except ValidationError as exc:
        problems += _describe(label, exc, (), CoreConfig)
    specs: list[ModuleSpec] = []
    for section, body in data.items():
        if section in CORE_SECTIONS:
            continue
        specs += _module_specs(label, section, body, modules_available, problems)
    if problems or core is None:
        raise ConfigError(problems)
    if core.machine.homing is None:  # Grbl's $22: on where the machine has homing switches
        core.machine.homing = any(spec.section == "endstops" for spec in specs)
    return Config(core, tuple(specs), path)


def _module_specs(
    label: str,
    section: str,
    body: Any,
    registry: Mapping[str, type[Module]],
    problems: list[str],
) -> list[ModuleSpec]:
    cls = registry.get(section)
    if cls is None:
        names = sorted([*CORE_SECTIONS, *registry])
        guess = _did_you_mean(section, names, "[{}]")
        problems.append(f"{label}: [{section}]: unknown section{guess} (known: {', '.join(names)})")
        return []
    if not isinstance(body, dict):
        problems.append(f"{label}: [{section}]: must be a table")
        return []
    if not cls.named:
        return _one_spec(label, cls, section, None, body, problems)
    if not body:
        problems.append(f"{label}: [{section}]: name each instance, as [{section}.NAME]")
    specs: list[ModuleSpec] = []
    for instance, instance_body in body.items():
        if not isinstance(instance_body, dict):
            problems.append(f"{label}: [{section}] {instance}: expected a [{section}.NAME] table")
            continue
        specs += _one_spec(label, cls, f"{section}.{instance}", instance, instance_body, problems)
    return specs


def _one_spec(
    label: str,
    cls: type[Module],
    section: str,
    instance: str | None,
    body: dict[str, Any],
    problems: list[str],
) -> list[ModuleSpec]:
    try:
        config = cls.Config.model_validate(body)
    except ValidationError as exc:
        problems += _describe(label, exc, (section,), cls.Config)
        return []
    return [ModuleSpec(cls, section, instance, config)]


def _describe(
    label: str, exc: ValidationError, prefix: tuple[str, ...], model: type[BaseModel]
) -> list[str]:
    """One line per pydantic error: ``FILE: [section] key: message``; an unknown key names the
    known key it is closest to."""
    lines = []
    for error in exc.errors():
        loc = prefix + tuple(str(part) for part in error["loc"])
        message = _message(error)
        if error["type"] == "extra_forbidden" and loc:
            parent = _model_at(model, tuple(str(part) for part in error["loc"][:-1]))
            if parent is not None:
                message += _did_you_mean(loc[-1], list(parent.model_fields), "{}")
        if isinstance(error.get("input"), dict) and error["type"] != "missing":
            lines.append(f"{label}: [{'.'.join(loc)}]: {message}" if loc else f"{label}: {message}")
        elif len(loc) == 0:
            lines.append(f"{label}: {message}")
        elif len(loc) == 1:
            lines.append(f"{label}: [{loc[0]}]: {message}")
        else:
            lines.append(f"{label}: [{'.'.join(loc[:-1])}] {loc[-1]}: {message}")
    return lines


def _did_you_mean(name: str, known: list[str], form: str) -> str:
    """`` (did you mean X?)`` for the closest known name, if one is close."""
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    return f" (did you mean {form.format(close[0])}?)" if close else ""


def _model_at(model: type[BaseModel], path: tuple[str, ...]) -> type[BaseModel] | None:
    """The model that validates the table at ``path`` (through ``dict[str, Model]`` tables
    such as ``[axes.x]`` and optional tables), or None."""
    current: Any = model
    for part in path:
        if _is_model(current):
            field = current.model_fields.get(part)
            if field is None:
                return None
            current = _table_type(field.annotation)
        elif get_origin(current) is dict:
            current = _table_type(get_args(current)[1])
        else:
            return None
    return current if _is_model(current) else None


def _table_type(annotation: Any) -> Any:
    """A model or ``dict`` from an annotation, looking inside ``X | None``."""
    if get_origin(annotation) in (Union, UnionType):
        return next((arg for arg in get_args(annotation)
                     if _is_model(arg) or get_origin(arg) is dict), None)
    return annotation


def _is_model(value: Any) -> bool:
    return isinstance(value, type) and issubclass(value, BaseModel)


def _message(error: Mapping[str, Any]) -> str:
    kind = error["type"]
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "missing required value"
    text = str(error["msg"]).removeprefix("Value error, ")
    if "input" in error and not isinstance(error["input"], dict):
        return f"{text} (got {error['input']!r})"
    return text
