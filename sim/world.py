"""The simulator's world: the grid of :mod:`koala_bridge.core.grid` and its JSON description.

The geometry (cells, walls as edges and segments, blocked cells, landmarks, magnetic sources, the
``[world]`` TOML form and its ASCII map) lives in ``core/grid.py``, where the firmware-side
estimators read it too; its names are re-exported here, their old home.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

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

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (answered by the Zenoh ``<prefix>/world`` queryable)."""
        return {
            "name": self.name,
            "cols": self.cols,
            "rows": self.rows,
            "cell_m": self.cell_m,
            "walls": [
                [c, r, s]
                for r in range(self.rows)
                for c in range(self.cols)
                for s in SIDES
                if self.has_wall(c, r, s)
            ],
            "segments": self.segments.tolist(),
            "blocked": sorted([list(b) for b in self.blocked]),
            "landmarks": [vars(lm) for lm in self.landmarks],
            "magnetic_sources": [vars(m) for m in self.magnetic_sources],
            "earth_field": vars(self.earth_field),
            "start": None if self.start is None else vars(self.start),
        }
