"""The grid world as plain data: square cells, walls, blocked cells, landmarks, magnetic sources.

The lowest layer (core): the simulator (``sim/world.py`` adds the world's JSON description) and
the firmware-side estimators (``estimation/``) both read the map from here, so an estimator
needs no simulator.

The grid follows the localisation lab (seeds/003_99eaf11f542ab395.txt, "Key values" A–D):
grid dimensions in cells, a cell length, landmarks with colour and position, and walls on any
cardinal side of a cell. Frames (docs/architecture.md): world x east, y north, metres; cell
``(col, row)`` with ``col = floor(x / cell_m)``, ``row = floor(y / cell_m)``, origin at the
south-west corner. (The lab's ``y = floor(-y / l)`` counts rows from the top; we count from the
bottom so that the world frame stays right-handed with y north.)

Walls are stored as *edges* so that a wall seen from either cell is the same wall:
``h`` edges are horizontal (the edge at ``y = r * cell_m`` spanning column ``c``),
``v`` edges are vertical (the edge at ``x = c * cell_m`` spanning row ``r``).

TOML form (``[world]`` of a config file)::

    [world]
    name = "open"
    cell_m = 0.5
    map = '''
    +---+---+
    |       |
    +   +---+
    | # |   |
    +---+---+
    '''
    walls = [[0, 1, "E"]]          # extra walls: [col, row, side]
    blocked = [[1, 0]]             # extra blocked cells
    start = { x = 0.25, y = 0.75, theta_deg = 0.0 }
    [[world.landmarks]]
    id = 1
    colour = "red"
    x = 0.0
    y = 1.0
    facing_deg = -45.0             # the direction the landmark's face looks, CCW from +x
    a_max_deg = 10000.0            # seeds/000 eq. 5: a very large a_max = omnidirectional
    [[world.magnetic_sources]]
    x = 1.0
    y = 0.5
    strength_uT = 5.0              # field magnitude at 1 m; falls with 1/d^2 (seeds/000 eq. 16)
    [world.earth_field]
    horizontal_uT = 20.0
    vertical_uT = -43.0            # z up: negative in the northern hemisphere
    north_deg = 90.0               # direction of magnetic north, CCW from +x (east)

The ASCII map is drawn north up: lines alternate between corner lines (``+`` with ``-`` runs
for walls) and cell lines (``|`` for walls, ``#`` inside a cell to block it); any other character
is an error naming its map line and column. Without a map, ``cols`` and ``rows`` give an empty
grid with its outer boundary walled.

Keys that may be left out, and their one default (config/README.md "Policy"): ``name``
("world"), ``walls`` and ``blocked`` ([]), ``start`` (none: ``[localisation] initial_pose`` must
then be given), ``start.theta_deg`` (0), ``landmarks`` and ``magnetic_sources`` ([]), a
landmark's ``colour`` (""), ``facing_deg`` (0) and ``a_max_deg`` (10000, omnidirectional), and
``earth_field`` and its keys (:class:`EarthField`: the values ``config/default.toml`` shows).
Numbers follow the schema's rules (:mod:`koala_bridge.core.schema`): finite, and no strings.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Self

import numpy as np
from koala_bridge.core.schema import (
    ConfigError,
    Int,
    PositiveInt,
    number,
    positive,
    reject_unknown,
    require,
    value_of,
)

SIDES = ("N", "E", "S", "W")
# Unit step (dcol, drow) towards each side.
SIDE_STEP: dict[str, tuple[int, int]] = {"N": (0, 1), "E": (1, 0), "S": (0, -1), "W": (-1, 0)}

Edge = tuple[str, int, int]  # ("h" | "v", c, r)


def side_edge(col: int, row: int, side: str) -> Edge:
    """The edge that is ``side`` of cell ``(col, row)``."""
    if side == "N":
        return ("h", col, row + 1)
    if side == "S":
        return ("h", col, row)
    if side == "E":
        return ("v", col + 1, row)
    if side == "W":
        return ("v", col, row)
    raise ConfigError(f"wall side must be one of {SIDES}, got {side!r}")


@dataclass(frozen=True)
class Landmark:
    """A camera landmark (seeds/003 "Landmarks": id, colour, position; seeds/000 "Perception error":
    an oriented face seen within ``a_max_deg`` of its facing direction)."""

    id: int
    colour: str
    x: float
    y: float
    facing_deg: float = 0.0
    a_max_deg: float = 10000.0


@dataclass(frozen=True)
class MagneticSource:
    """A local magnetic source: horizontal field of ``strength_uT`` at 1 m, falling with 1/d^2
    (seeds/000 eq. 16), pointing from the robot towards the source (negative strength: away)."""

    x: float
    y: float
    strength_uT: float


@dataclass(frozen=True)
class EarthField:
    """The Earth field: horizontal strength, vertical component (z up) and magnetic north."""

    horizontal_uT: float = 20.0
    vertical_uT: float = -43.0
    north_deg: float = 90.0

    def vector_world(self) -> np.ndarray:
        """Field in the world frame (x east, y north, z up), microtesla."""
        a = math.radians(self.north_deg)
        return np.array(
            [self.horizontal_uT * math.cos(a), self.horizontal_uT * math.sin(a), self.vertical_uT]
        )


@dataclass(frozen=True)
class StartPose:
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class Grid:
    """A grid world. Build with :meth:`from_dict`; every field is immutable."""

    name: str
    cols: int
    rows: int
    cell_m: float
    edges: frozenset[Edge]
    blocked: frozenset[tuple[int, int]]
    landmarks: tuple[Landmark, ...] = ()
    magnetic_sources: tuple[MagneticSource, ...] = ()
    earth_field: EarthField = field(default_factory=EarthField)
    start: StartPose | None = None
    segments: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        segs = []
        m = self.cell_m
        for kind, c, r in sorted(self.edges):
            if kind == "h":
                segs.append((c * m, r * m, (c + 1) * m, r * m))
            else:
                segs.append((c * m, r * m, c * m, (r + 1) * m))
        arr = np.array(segs, dtype=float).reshape(-1, 4)
        arr.flags.writeable = False
        object.__setattr__(self, "segments", arr)

    # --- geometry ---------------------------------------------------------------------------
    @property
    def width_m(self) -> float:
        return self.cols * self.cell_m

    @property
    def height_m(self) -> float:
        return self.rows * self.cell_m

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """The cell containing world point ``(x, y)`` (may be outside the grid)."""
        return (math.floor(x / self.cell_m), math.floor(y / self.cell_m))

    def cell_centre(self, col: int, row: int) -> tuple[float, float]:
        return ((col + 0.5) * self.cell_m, (row + 0.5) * self.cell_m)

    def in_bounds(self, col: int, row: int) -> bool:
        return 0 <= col < self.cols and 0 <= row < self.rows

    def has_wall(self, col: int, row: int, side: str) -> bool:
        """True when ``side`` of cell ``(col, row)`` is a wall (the grid boundary counts only
        where the map draws it)."""
        return side_edge(col, row, side) in self.edges

    def wall_signature(self, col: int, row: int) -> tuple[bool, bool, bool, bool]:
        """Walls on the N, E, S, W sides of a cell, in that order (seeds/003 "Cell Walls")."""
        return tuple(self.has_wall(col, row, s) for s in SIDES)  # type: ignore[return-value]

    def can_move(self, col: int, row: int, side: str) -> bool:
        """True when the robot can go from ``(col, row)`` to its neighbour on ``side``."""
        dc, dr = SIDE_STEP[side]
        n = (col + dc, row + dr)
        return (
            self.in_bounds(*n) and n not in self.blocked and not self.has_wall(col, row, side)
        )

    def reachable(self, start: tuple[int, int]) -> set[tuple[int, int]]:
        """Every cell the robot can drive to from ``start`` (``start`` included), through
        open sides (:meth:`can_move`)."""
        seen, todo = {start}, [start]
        while todo:
            c = todo.pop()
            for side in SIDES:
                dc, dr = SIDE_STEP[side]
                n = (c[0] + dc, c[1] + dr)
                if n not in seen and self.can_move(*c, side):
                    seen.add(n)
                    todo.append(n)
        return seen

    def walled_sides(self) -> list[tuple[int, int, str]]:
        """``(col, row, side)`` of every walled cell side, row by row from the south, column
        fastest, sides in N, E, S, W order (a wall between two cells is listed for both)."""
        return [
            (c, r, s)
            for r in range(self.rows)
            for c in range(self.cols)
            for s in SIDES
            if self.has_wall(c, r, s)
        ]

    def free_cells(self) -> list[tuple[int, int]]:
        return [
            (c, r) for r in range(self.rows) for c in range(self.cols) if (c, r) not in self.blocked
        ]

    # --- (de)serialisation --------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Self:
        """Build a world from the ``[world]`` table of a config (see the module docstring)."""
        sec = "world"
        reject_unknown(
            d,
            ["name", "cell_m", "map", "cols", "rows", "walls", "blocked", "start", "landmarks",
             "magnetic_sources", "earth_field"],
            sec,
        )
        cell_m = positive(require(d, "cell_m", sec), "cell_m", sec)
        edges: set[Edge] = set()
        blocked: set[tuple[int, int]] = set()
        if "map" in d:
            if "cols" in d or "rows" in d:
                raise ConfigError("[world] give either 'map' or 'cols'/'rows', not both")
            if not isinstance(d["map"], str):
                raise ConfigError("[world] 'map' is a multi-line string (the ASCII map)")
            cols, rows, map_edges, map_blocked = parse_ascii_map(d["map"])
            edges |= map_edges
            blocked |= map_blocked
        else:
            cols = value_of(PositiveInt, require(d, "cols", sec), "cols", sec)
            rows = value_of(PositiveInt, require(d, "rows", sec), "rows", sec)
            for c in range(cols):
                edges.add(("h", c, 0))
                edges.add(("h", c, rows))
            for r in range(rows):
                edges.add(("v", 0, r))
                edges.add(("v", cols, r))
        for w in _array(d, "walls", sec):
            if not (isinstance(w, list | tuple) and len(w) == 3 and isinstance(w[2], str)):
                raise ConfigError(f"[world] each wall is [col, row, side], got {w!r}")
            side = w[2].upper()
            if side not in SIDES:
                raise ConfigError(f"[world] a wall's side is one of {', '.join(SIDES)}, got {w!r}")
            col, row = (value_of(Int, v, "walls", sec) for v in w[:2])
            edges.add(side_edge(col, row, side))
        for b in _array(d, "blocked", sec):
            if not (isinstance(b, list | tuple) and len(b) == 2):
                raise ConfigError(f"[world] each blocked cell is [col, row], got {b!r}")
            blocked.add((value_of(Int, b[0], "blocked", sec), value_of(Int, b[1], "blocked", sec)))
        for c, r in blocked:
            if not (0 <= c < cols and 0 <= r < rows):
                raise ConfigError(
                    f"[world] blocked cell {(c, r)} is outside the {cols}x{rows} grid")
            edges.update(side_edge(c, r, s) for s in SIDES)
        landmarks = tuple(_landmark(_table(x, f"world.landmarks[{i}]"), i)
                          for i, x in enumerate(_array(d, "landmarks", sec)))
        ids = [lm.id for lm in landmarks]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"[world.landmarks] landmark ids must be unique, got {ids}")
        sources = tuple(_source(_table(x, f"world.magnetic_sources[{i}]"), i)
                        for i, x in enumerate(_array(d, "magnetic_sources", sec)))
        ef = _table(d.get("earth_field", {}), "world.earth_field")
        reject_unknown(ef, ["horizontal_uT", "vertical_uT", "north_deg"], "world.earth_field")
        earth = EarthField(**{k: number(v, k, "world.earth_field") for k, v in ef.items()})
        start = None
        if "start" in d:
            s = _table(d["start"], "world.start")
            reject_unknown(s, ["x", "y", "theta_deg"], "world.start")
            start = StartPose(
                number(require(s, "x", "world.start"), "x", "world.start"),
                number(require(s, "y", "world.start"), "y", "world.start"),
                math.radians(number(s.get("theta_deg", 0.0), "theta_deg", "world.start")),
            )
        return cls(
            name=_name(d.get("name", "world")),
            cols=cols,
            rows=rows,
            cell_m=cell_m,
            edges=frozenset(edges),
            blocked=frozenset(blocked),
            landmarks=landmarks,
            magnetic_sources=sources,
            earth_field=earth,
            start=start,
        )


def _name(value: Any) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"[world] 'name' is a string, got {type(value).__name__} {value!r}")
    return value


def _array(d: Mapping[str, Any], key: str, sec: str) -> list[Any]:
    """``d[key]`` (default []), which must be an array."""
    value = d.get(key, [])
    if not isinstance(value, list):
        raise ConfigError(f"[{sec}] '{key}' is an array, got {type(value).__name__} {value!r}")
    return value


def _table(value: Any, sec: str) -> Mapping[str, Any]:
    """``value``, which must be a table (``[{sec}]`` or an inline ``{...}``)."""
    if not isinstance(value, Mapping):
        raise ConfigError(f"[{sec}] is a table, got {type(value).__name__} {value!r}")
    return value


def _landmark(d: Mapping[str, Any], i: int) -> Landmark:
    sec = f"world.landmarks[{i}]"
    reject_unknown(d, ["id", "colour", "x", "y", "facing_deg", "a_max_deg"], sec)
    return Landmark(
        id=value_of(Int, require(d, "id", sec), "id", sec),
        colour=str(d.get("colour", "")),
        x=number(require(d, "x", sec), "x", sec),
        y=number(require(d, "y", sec), "y", sec),
        facing_deg=number(d.get("facing_deg", 0.0), "facing_deg", sec),
        a_max_deg=positive(d.get("a_max_deg", 10000.0), "a_max_deg", sec),
    )


def _source(d: Mapping[str, Any], i: int) -> MagneticSource:
    sec = f"world.magnetic_sources[{i}]"
    reject_unknown(d, ["x", "y", "strength_uT"], sec)
    return MagneticSource(
        number(require(d, "x", sec), "x", sec), number(require(d, "y", sec), "y", sec),
        number(require(d, "strength_uT", sec), "strength_uT", sec),
    )


def parse_ascii_map(text: str) -> tuple[int, int, set[Edge], set[tuple[int, int]]]:
    """Parse a north-up ASCII map into ``(cols, rows, edges, blocked)``.

    Corner lines hold ``+`` at every grid corner with runs of ``-`` where a horizontal wall is;
    cell lines hold ``|`` where a vertical wall is and ``#`` inside a blocked cell. All corner
    lines must put their ``+`` in the same columns. Any other character, or one of these where it
    means nothing (a ``#`` in a wall slot, a ``-`` on a cell line), is an error naming its map
    line and column: a typo must not silently change the world.
    """
    lines = [ln.rstrip() for ln in text.strip("\n").splitlines()]
    lines = [ln for ln in lines if ln.strip()]
    if len(lines) < 3 or len(lines) % 2 == 0:
        raise ConfigError("[world] map must alternate corner lines and cell lines, "
                          "starting and ending with a corner line")
    corners = [i for i, ch in enumerate(lines[0]) if ch == "+"]
    if len(corners) < 2:
        raise ConfigError("[world] map's first line must contain at least two '+' corners")
    cols = len(corners) - 1
    rows = (len(lines) - 1) // 2
    edges: set[Edge] = set()
    blocked: set[tuple[int, int]] = set()
    for li, line in enumerate(lines):
        padded = line.ljust(corners[-1] + 1)
        if li % 2 == 0:
            if [i for i, ch in enumerate(padded) if ch == "+"] != corners:
                raise ConfigError(f"[world] map line {li + 1}: '+' corners do not line up")
            y_index = rows - li // 2
            for c in range(cols):
                span = padded[corners[c] + 1 : corners[c + 1]]
                side = f"south of cell ({c}, {y_index})" if y_index < rows else (
                    f"north of cell ({c}, {rows - 1})")
                _check_map_chars(span, " -", li, corners[c] + 1, f"the wall slot {side}")
                if "-" in span:
                    edges.add(("h", c, y_index))
        else:
            row = rows - 1 - li // 2
            for k, pos in enumerate(corners):
                side = (f"west of cell ({k}, {row})" if k < cols
                        else f"east of cell ({k - 1}, {row})")
                _check_map_chars(padded[pos], " |", li, pos, f"the wall slot {side}")
                if padded[pos] == "|":
                    edges.add(("v", k, row))
            for c in range(cols):
                span = padded[corners[c] + 1 : corners[c + 1]]
                _check_map_chars(span, " #", li, corners[c] + 1, f"cell ({c}, {row})")
                if "#" in span:
                    blocked.add((c, row))
        _check_map_chars(padded[corners[-1] + 1 :], " ", li, corners[-1] + 1,
                         "the map's right margin (beyond the last corner)")
    return cols, rows, edges, blocked


def _check_map_chars(span: str, allowed: str, line: int, start: int, where: str) -> None:
    """Raise if ``span`` (map line ``line``, 0-based, from text column ``start``) holds a
    character not in ``allowed``."""
    for i, ch in enumerate(span):
        if ch not in allowed:
            expected = " or ".join(repr(a) for a in allowed)
            raise ConfigError(
                f"[world] map line {line + 1}, column {start + i + 1}: {ch!r} in {where} "
                f"(expected {expected}; '+' corners, '-' and '|' walls, '#' blocked cell)"
            )
