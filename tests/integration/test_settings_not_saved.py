"""A ``$x=`` that cannot be saved (a full disk) answers an error and keeps the old value."""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from server.config_loader import load_config
from server.errors import CommandError, Error
from tests.conftest import REPO
from tests.support.helpers import running, submit_all


@contextlib.contextmanager
def full_folder(tmp_path: Path) -> Iterator[Path]:
    """A folder on a full file system: a 64 KiB tmpfs filled up (as root), else a folder this
    user may not write (the same refusal, EACCES instead of ENOSPC)."""
    folder = tmp_path / "full"
    folder.mkdir()
    if os.geteuid() != 0:
        yield folder
        return
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(folder)], check=True)
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def _fill(folder: Path) -> None:
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return
    with (folder / "filler").open("wb", buffering=0) as filler, pytest.raises(OSError) as info:
        while True:
            filler.write(b"\0" * 4096)
    assert info.value.errno == errno.ENOSPC


async def test_a_setting_that_cannot_be_saved_answers_an_error_and_keeps_the_old_value(
        tmp_path: Path) -> None:
    with full_folder(tmp_path) as folder:
        config_file = folder / "machine.toml"
        config_file.write_text((REPO / "examples" / "plotter.toml").read_text())
        async with running(load_config(config_file)) as app:
            before = await submit_all(app, ["$$"])
            _fill(folder)
            with pytest.raises(CommandError) as info:
                await submit_all(app, ["$110=6000"])
            assert info.value.code == Error.SETTING_NOT_SAVED
            assert "the old value is kept" in str(info.value)
            assert await submit_all(app, ["$$"]) == before
        assert sorted(path.name for path in folder.iterdir()
                      if path.name.endswith(".tmp")) == []
        assert not (folder / "machine.settings.toml").exists()
