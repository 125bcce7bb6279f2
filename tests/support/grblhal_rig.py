"""Real grblHAL for the tests: the grblhal-sim rig in ``../shared/rigs/grblhal-sim``.

As :mod:`tests.support.grbl_rig` for Grbl 1.1h: :func:`rig_executable` builds it once into the
repository's ignored ``build/`` folder, :func:`grblhal_on_pty` runs a fresh board (its settings
in a temporary folder) on a pseudo-terminal, :func:`grblhal_direct` one on pipes with a
:class:`~tests.support.grbl_rig.GrblClient` past its banner. grblHAL reads input from a second
after it starts; its banner is ``GrblHAL 1.1f ['$' or '$HELP' for help]``.
"""

from __future__ import annotations

import contextlib
import subprocess
from pathlib import Path

from tests.support.grbl_rig import GrblClient, board_direct, board_on_pty
from tests.support.rigs import REPO, RIGS, rig

RIG = RIGS / "grblhal-sim"
BUILD = REPO / "build" / "grblhal-sim"


def rig_executable() -> Path:
    """The built simulator; skips the test only when the rigs folder is absent."""
    rig("grblhal-sim")
    done = subprocess.run([str(RIG / "build"), str(BUILD)], capture_output=True, text=True,
                          timeout=900, check=True)
    return Path(done.stdout.strip().splitlines()[-1])


def _command(exe: Path) -> list[str]:
    return [str(exe), "-n", "-e", "EEPROM.DAT", "-b", "/dev/null", "-s", "/dev/null"]


def grblhal_on_pty(tmp_path: Path, name: str = "grblhal"
                   ) -> contextlib.AbstractAsyncContextManager[str]:
    """A fresh grblHAL board on a pseudo-terminal (it reads input a second after it starts)."""
    return board_on_pty(_command(rig_executable()), tmp_path / f"{name}-settings", 1.2)


def grblhal_direct(tmp_path: Path, name: str = "direct"
                   ) -> contextlib.AbstractAsyncContextManager[GrblClient]:
    """A fresh grblHAL board on pipes, past its banner and its first second."""
    return board_direct(_command(rig_executable()), tmp_path / f"{name}-settings", 1.0)
