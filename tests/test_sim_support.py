"""Helpers for the simulator tests (no tests here): configs built from config/default.toml."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

DEFAULT = Path(__file__).resolve().parents[1] / "config" / "default.toml"


def default_config() -> dict[str, Any]:
    with DEFAULT.open("rb") as f:
        return tomllib.load(f)


def config_with_world(world: dict[str, Any], **sim: Any) -> dict[str, Any]:
    """The default config with another ``[world]`` (and ``[sim]`` overrides)."""
    cfg = copy.deepcopy(default_config())
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
