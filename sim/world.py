"""The simulator's world: the grid of :mod:`koala_bridge.core.grid` and its JSON description.

The geometry (cells, walls as edges and segments, blocked cells, landmarks, magnetic sources, the
``[world]`` TOML form and its ASCII map) lives in ``core/grid.py``, where the firmware-side
estimators read it too; its names are re-exported here, their old home.
"""

from __future__ import annotations

from dataclasses import dataclass

from koala_bridge.core.grid import (
    SIDE_STEP,
    SIDES,
    EarthField,
    Edge,
    Grid,
    Landmark,
    MagneticSource,
    StartPose,
    parse_ascii_map,
    side_edge,
)

__all__ = [
    "SIDES",
    "SIDE_STEP",
    "EarthField",
    "Edge",
    "Grid",
    "Landmark",
    "MagneticSource",
    "StartPose",
    "World",
    "parse_ascii_map",
    "side_edge",
]


@dataclass(frozen=True)
class World(Grid):
    """The simulated world: a :class:`~koala_bridge.core.grid.Grid` (build with
    :meth:`from_dict`)."""

