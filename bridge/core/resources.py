"""The shipped configuration files, found through :mod:`importlib.resources`.

``config/`` of the repository is installed as the data package :mod:`koala_bridge.config`; these
helpers return real filesystem paths into it, so the same code finds ``default.toml``, the worlds
and ``koala.dbc`` in a checkout, an editable install and a wheel in any ``site-packages``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

CONFIG_PACKAGE = "koala_bridge.config"


def config_dir() -> Path:
    """The folder of the shipped configuration (``default.toml``, ``ideal.toml``, ``worlds/``,
    ``koala.dbc``). Installed packages are plain folders (pip unpacks wheels), so this is a path a
    user can open, copy or name in an endpoints file."""
    return Path(str(files(CONFIG_PACKAGE)))


def default_config_path() -> Path:
    """``default.toml``: the Koala with every sensor model on, the run's default ``--config``."""
    return config_dir() / "default.toml"


def default_dbc_path() -> Path:
    """``koala.dbc``: the Koala's CAN database, the default of ``[buses.can] dbc``."""
    return config_dir() / "koala.dbc"
