"""Where motiond keeps its files: the data folder, the job files, the settings, the configs.

One place decides every path, so a test (or a second server on one host) that gives its server
its own data folder moves every file motiond writes. The folders follow the platform's rules
(``platformdirs``: ``$XDG_DATA_HOME/motiond``, else ``~/.local/share/motiond`` on Linux):

- the data folder: ``[jobs] data_dir`` (``--data-dir``, ``$MOTIOND_DATA_DIR``), else the
  user's data folder. It holds ``jobs/`` (the job files, nothing else) and ``settings.toml``
  (the ``$x=`` settings of the embedded default machine); other parts add their files here
  through :func:`data_dir`.
- configs: ``--config FILE`` (``$MOTIOND_CONFIG``), else the first ``motiond.toml`` found in
  :func:`config_search_path` (the working directory, the user's config folder, then
  ``/etc/motiond``), else the embedded default.
"""

from __future__ import annotations

import logging
from pathlib import Path

import platformdirs

from server.config import Config, CoreConfig

log = logging.getLogger("motiond.paths")
APP = "motiond"
CONFIG_NAME = "motiond.toml"
SYSTEM_CONFIG_DIR = Path("/etc/motiond")


def data_dir(core: CoreConfig) -> Path:
    """motiond's data folder for this machine (not created here)."""
    if core.jobs.data_dir is not None:
        return core.jobs.data_dir.expanduser()
    return Path(platformdirs.user_data_path(APP))


def jobs_dir(core: CoreConfig) -> Path:
    """The job files: a folder of their own, so no other file is ever listed as a job."""
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
    return [
        Path.cwd() / CONFIG_NAME,
        platformdirs.user_config_path(APP) / CONFIG_NAME,
        SYSTEM_CONFIG_DIR / CONFIG_NAME,
    ]


def find_config() -> Path | None:
    """The first config of :func:`config_search_path` that exists, else None (embedded)."""
    return next((path for path in config_search_path() if path.is_file()), None)


def log_dir() -> Path:
    """The user's log folder (``$XDG_STATE_HOME/motiond/log``), for ``--log-file`` defaults."""
    return Path(platformdirs.user_log_path(APP))
