"""Where motiond keeps its files: the data folder, the job files, the settings, the configs.

One place decides every path, so a test (or a second server on one host) that gives its server
its own data folder moves every file motiond writes. The folders follow the platform's rules
(``platformdirs``: ``$XDG_DATA_HOME/motiond``, else ``~/.local/share/motiond`` on Linux):

- the data folder: ``[jobs] data_dir`` (``--data-dir``, ``$MOTIOND_DATA_DIR``), else the
  user's data folder. It holds ``jobs/`` (the job files, nothing else, unless ``[jobs]
  jobs_dir`` puts them elsewhere: Moonraker's ``gcodes`` folder) and ``settings.toml``
  (the ``$x=`` settings of the embedded default machine); other parts add their files here
  through :func:`data_dir`.
- configs: ``--config FILE`` (``$MOTIOND_CONFIG``), else the first ``motiond.toml`` found in
  :func:`config_search_path` (the working directory, the user's config folder, then
  ``/etc/motiond``), else the embedded default.
"""

from __future__ import annotations

import logging
import os
import stat
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import platformdirs

from server.errors import ConfigError

if TYPE_CHECKING:  # the health check imports this module: no pydantic at run time
    from server.config import Config, CoreConfig

log = logging.getLogger("motiond.paths")
APP = "motiond"
CONFIG_NAME = "motiond.toml"
SYSTEM_CONFIG_DIR = Path("/etc/motiond")


def data_dir(core: CoreConfig) -> Path:
    """motiond's data folder for this machine (not created here)."""
    if core.jobs.data_dir is not None:
        return core.jobs.data_dir.expanduser()
    folder = _user_folder(platformdirs.user_data_path)
    if folder is None:
        raise ConfigError([
            f"no data folder: uid {os.getuid()} has no home folder (no account and $HOME "
            "unset); give one with --data-dir, $MOTIOND_DATA_DIR or [jobs] data_dir, or set "
            "HOME"])
    return folder


def _user_folder(where: Callable[[str], Path]) -> Path | None:
    """A folder of this user's (platformdirs'), or None when there is no home to put it in:
    a uid without an account (``docker run --user 1000``, Kubernetes' runAsUser) and no
    ``$HOME``. Looked up only when a path is needed, so such a uid runs all that needs none."""
    try:
        return Path(where(APP))
    except (RuntimeError, KeyError):
        return None


def jobs_dir(core: CoreConfig) -> Path:
    """The job files: a folder of their own, so no other file is ever listed as a job
    (``[jobs] jobs_dir``, e.g. Moonraker's ``gcodes`` folder, else the data folder's ``jobs/``)."""
    if core.jobs.jobs_dir is not None:
        return core.jobs.jobs_dir.expanduser()
    return data_dir(core) / "jobs"


def materials_path(core: CoreConfig) -> Path:
    """The material library of drawing imports (layer settings by name): in the data folder."""
    return data_dir(core) / "materials.json"


def settings_path(config: Config) -> Path:
    """Where ``$x=value`` settings persist: beside the config file, else in the data folder."""
    if config.path is not None:
        return config.path.with_name(config.path.stem + ".settings.toml")
    folder = data_dir(config.core)
    path = folder / "settings.toml"
    old = folder / ".settings.toml"  # before motiond 0.1.1: hidden among the job files
    if old.is_file() and not path.exists():
        old.rename(path)
        log.info("settings moved from %s to %s", old, path)
    return path


def config_search_path() -> list[Path]:
    """Where ``motiond.toml`` is looked for when no config is named, first match wins."""
    user = _user_folder(platformdirs.user_config_path)
    return [
        Path.cwd() / CONFIG_NAME,
        *([user / CONFIG_NAME] if user is not None else []),
        SYSTEM_CONFIG_DIR / CONFIG_NAME,
    ]


def find_config() -> Path | None:
    """The first config of :func:`config_search_path` that exists, else None (embedded)."""
    return next((path for path in config_search_path() if path.is_file()), None)


def log_dir() -> Path:
    """The user's log folder (``$XDG_STATE_HOME/motiond/log``), for ``--log-file`` defaults."""
    folder = _user_folder(platformdirs.user_log_path)
    if folder is None:
        raise ConfigError(["no log folder: uid without a home folder; give --log-file"])
    return folder


def check_config_file(path: Path, uid: int | None = None) -> None:
    """Refuse a config another account could have written, as ssh refuses such a key: the
    file must belong to ``uid`` (default: this process's) or root, and others may not write
    it. A config names the machine's limits, its backend and who may control it."""
    uid = os.geteuid() if uid is None else uid
    try:
        info = path.stat()
    except OSError:
        return  # reading it says why
    problem = None
    if info.st_uid not in (uid, 0):
        problem = f"owned by uid {info.st_uid}, not by the account that runs motiond ({uid}) " \
                  f"or root: sudo chown {uid} {path}"
    elif info.st_mode & stat.S_IWOTH:
        problem = f"writable by every account (mode {stat.S_IMODE(info.st_mode):04o}): " \
                  f"chmod o-w {path}"
    if problem:
        raise ConfigError([f"{path}: refusing a config file {problem}"])
