"""Helpers for the simulator tests (no tests here): configs built from config/default.toml (every
error model on) and config/ideal.toml (every model off). A test that compares readings with exact
geometry says so by using :func:`ideal_config` (or ``ideal=True``)."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

CONFIG = Path(__file__).resolve().parents[1] / "config"
DEFAULT = CONFIG / "default.toml"
IDEAL = CONFIG / "ideal.toml"


def default_config() -> dict[str, Any]:
    """config/default.toml: every error model on."""
    with DEFAULT.open("rb") as f:
        return tomllib.load(f)


def ideal_config() -> dict[str, Any]:
    """config/ideal.toml: the default world and robot with every sensor and the drive ideal."""
    with IDEAL.open("rb") as f:
        return tomllib.load(f)


def config_with_world(world: dict[str, Any], *, ideal: bool, **sim: Any) -> dict[str, Any]:
    """A config with another ``[world]`` (and ``[sim]`` overrides), from config/ideal.toml when
    ``ideal`` (every caller says which), else from config/default.toml (every model on)."""
    cfg = copy.deepcopy(ideal_config() if ideal else default_config())
    cfg["world"] = world
    cfg["sim"].update(sim)
    return cfg


def box_world(cols: int = 12, rows: int = 12, x: float = 3.0, y: float = 3.0,
              theta_deg: float = 0.0, **extra: Any) -> dict[str, Any]:
    """An empty walled box of 0.5 m cells (6 m x 6 m by default) with the robot at (x, y)."""
    w = {"name": "box", "cell_m": 0.5, "cols": cols, "rows": rows,
         "start": {"x": x, "y": y, "theta_deg": theta_deg}}
    w.update(extra)
    return w
