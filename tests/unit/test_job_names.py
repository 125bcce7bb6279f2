"""Job names that are not what they look like, or that name a device elsewhere, are refused."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.errors import CommandError, Error
from server.jobs.store import JobStore, valid_name


@pytest.mark.parametrize(("name", "why"), [
    ("CON", "device name"), ("NUL.nc", "device name"), ("com1.gcode", "device name"),
    ("lpt¹.nc", "device name"), ("aux.tar.gz", "device name"),
    ("\u202egnp.nc", "U+202E"),  # shown as "cn.png" by a right-to-left override
    ("job\u2066.nc", "U+2066"), ("x\u200b.nc", "U+200B"), ("x\ufeff.nc", "U+FEFF"),
    ("job\uff0enc", "looks like a dot"), ("job\u2024nc", "looks like a dot"),
    ("job\ufe52nc", "looks like a dot"), ("job\u3002nc", "looks like a dot"),
    ("job.", "ends with a dot"),
])
def test_misleading_and_device_job_names_are_refused(
        tmp_path: Path, name: str, why: str) -> None:
    with pytest.raises(CommandError) as info:
        JobStore(tmp_path, 1000).path(name)
    assert info.value.code == Error.FILE_ERROR and why in str(info.value)
    assert not valid_name(name)  # nor listed, should one be on disk


@pytest.mark.parametrize("name", ["job.nc", "console.nc", "nul_box.nc", "résumé.nc",
                                  "日本語.gcode", "con-test.nc", "a b.nc"])
def test_ordinary_names_still_pass(tmp_path: Path, name: str) -> None:
    assert JobStore(tmp_path, 1000).path(name).name == name
    assert valid_name(name)
