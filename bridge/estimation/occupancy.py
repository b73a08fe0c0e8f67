"""Occupancy-grid mapping from range readings (seeds/004 "Sensor Model Implementation").

Each reading ``d`` of a sensor at ``(x_s, y_s)`` looking along ``phi`` (the robot's heading plus
the sensor's mounting yaw) is spread, as the lecture does, over the beam arc of width ``sigma``
(beam-width error) and over the range band ``d (1 - eps) .. d (1 + eps)`` (distance error, ``eps``
the sensor's relative error: IR 3 %, sonar 6.6 %)::

    for r in d(1-eps) .. d(1+eps) step INC:          # INC < one cell: no cell is skipped
        for a in -sigma/2 .. sigma/2 step omega:      # omega: about half a cell of arc at r
            mark cell(x_s + r cos(phi + a), y_s + r sin(phi + a)) occupied

Unlike the lecture's ``set grid = 1``, cells accumulate evidence in log-odds (seeds/003 A). A
reading says that an obstacle is *somewhere* on its arc, not everywhere on it, so the arc band's
``n`` distinct cells share the evidence: each gains ``l_occ * min(1, occ_share_cells / n)`` once
per reading (the lab's "distributed evenly among matching cells"). A narrow IR beam's band is a
cell or two and gets the full ``l_occ``; a 23 deg sonar arc at 1 m spans ~8 cells of 5 cm and each
gets ~3/8 of it, so the free space beside a wall it saw is not painted occupied. Every cell of
the cone *in front of* the band -- radii ``0 .. d (1 - eps)`` -- gains ``l_free`` (negative). A
cell in both sets counts as occupied. A
reading with no echo (nan, inf, or ``>= max_range_m``) marks nothing unless
``mark_free_on_no_echo``: sonar loses echoes by specular reflection (seeds/004 "Reflection
Errors"), so a missing echo is weak evidence of free space. Log-odds are clamped to
``[l_min, l_max]`` so the map stays responsive and fits the int8 encoding.

Grid layout: array ``[row, col]``, row 0 the southern-most, origin at the south-west corner
(docs/architecture.md), ``resolution_m`` metres per cell (finer than the world's cells).
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.grid import Grid
from koala_bridge.estimation.errors import EstimationError
from koala_bridge.estimation.probability import prob_from_log_odds
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class BeamModel:
    """A range sensor's beam as the lecture models it.

    Attributes:
        beam_width_rad: full cone angle ``sigma`` (Khepera IR 1.72 deg, sonar 22.9 deg in
            seeds/004).
        range_error: relative distance error ``eps`` (IR 0.03, sonar 0.066, seeds/004 tables).
        max_range_m: readings at or beyond this, and nan/inf, are "no echo".
        min_range_m: readings below this are ignored (the Koala's sonar reads 0 under 25 cm).
    """

    beam_width_rad: float
    range_error: float
    max_range_m: float
    min_range_m: float = 0.0

    def __post_init__(self) -> None:
        if (
            self.beam_width_rad < 0
            or self.range_error < 0
            or not self.max_range_m > self.min_range_m >= 0
        ):
            raise EstimationError(f"invalid beam model {self}")


@dataclass(frozen=True)
class OccupancyParams:
    """Log-odds increments and clamps.

    Attributes:
        l_occ: added to a cell in a reading's obstacle band (0.85 = ln(0.7/0.3)).
        l_free: added to a cell in front of the band (-0.4 ~ ln(0.4/0.6)).
        occ_share_cells: an arc band of ``n`` cells gives each ``l_occ * min(1, this / n)``.
        free_margin_cells: the free cone stops this many cells short of the band (the obstacle's
            half thickness, Thrun et al. 2005 table 9.2 ``alpha / 2``), so beams grazing a wall
            do not clear the cells the wall touches.
        l_min, l_max: clamp of the accumulated log-odds.
        mark_free_on_no_echo: whether a no-echo reading clears its whole cone to ``max_range_m``.
    """

    l_occ: float = 0.85
    l_free: float = -0.4
    occ_share_cells: float = 3.0
    free_margin_cells: float = 0.0
    l_min: float = -4.0
    l_max: float = 4.0
    mark_free_on_no_echo: bool = False


def _cells(xs: FloatArray, ys: FloatArray, shape: tuple[int, int], resolution_m: float) -> IntArray:
    """Flat row-major indices of the distinct in-grid cells containing the points."""
    rows, cols = shape
    c = np.floor(xs / resolution_m).astype(np.int64)
    r = np.floor(ys / resolution_m).astype(np.int64)
    ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
    return np.unique(r[ok] * cols + c[ok])


def _arc_points(
    xs: float, ys: float, phi: float, radii: FloatArray, sigma: float, step_m: float
) -> tuple[FloatArray, FloatArray]:
    """Points on arcs of the given radii across the beam, about ``step_m`` apart along the arc."""
    r_max = float(np.max(radii)) if radii.size else 0.0
    n_a = max(1, math.ceil(sigma * r_max / step_m) + 1) if sigma > 0 else 1
    angles = np.linspace(-sigma / 2, sigma / 2, n_a) if n_a > 1 else np.zeros(1)
    rr, aa = np.meshgrid(radii, phi + angles, indexing="ij")
    return xs + rr * np.cos(aa), ys + rr * np.sin(aa)


def beam_cells(
    shape: tuple[int, int],
    resolution_m: float,
    sensor_xy: tuple[float, float],
    phi: float,
    range_m: float,
    beam: BeamModel,
    mark_free_on_no_echo: bool = False,
    free_margin_m: float = 0.0,
) -> tuple[IntArray, IntArray]:
    """The cells one reading marks occupied and free (module docstring).

    Args:
        shape: ``(rows, cols)`` of the grid.
        resolution_m: cell side, metres; the grid's origin is world ``(0, 0)``.
        sensor_xy: sensor position, world frame, metres (not the robot's centre).
        phi: beam axis, rad CCW from east (robot heading + sensor yaw).
        range_m: the reading, metres; nan/inf/``>= beam.max_range_m`` = no echo;
            ``< beam.min_range_m`` = ignored.
        beam: the sensor's beam model.
        mark_free_on_no_echo: clear the cone to ``max_range_m`` on no echo.
        free_margin_m: the free cone ends this far short of the band.

    Returns:
        ``(occupied, free)``: flat row-major cell indices, disjoint and sorted.
    """
    xs, ys = sensor_xy
    empty = np.zeros(0, dtype=np.int64)
    no_echo = not math.isfinite(range_m) or range_m >= beam.max_range_m
    if not no_echo and range_m < beam.min_range_m:
        return empty, empty
    if no_echo:
        if not mark_free_on_no_echo:
            return empty, empty
        free_to = beam.max_range_m
        occ = empty
    else:
        d = max(range_m, 0.0)
        lo, hi = d * (1.0 - beam.range_error), d * (1.0 + beam.range_error)
        inc = resolution_m / 4.0  # seeds/004: "choose an INC which is less than 1"
        radii = np.linspace(lo, hi, max(2, math.ceil((hi - lo) / inc) + 1))
        ox, oy = _arc_points(xs, ys, phi, radii, beam.beam_width_rad, resolution_m / 2.0)
        occ = _cells(ox.ravel(), oy.ravel(), shape, resolution_m)
        free_to = lo - free_margin_m
    n_r = math.ceil(free_to / (resolution_m / 2.0))
    if n_r < 1:
        return occ, empty
    radii = np.linspace(0.0, free_to, n_r + 1)[:-1]
    fx, fy = _arc_points(xs, ys, phi, radii, beam.beam_width_rad, resolution_m / 2.0)
    free = np.setdiff1d(_cells(fx.ravel(), fy.ravel(), shape, resolution_m), occ)
    return occ, free


def encode_log_odds(log_odds: FloatArray, l_max: float) -> tuple[str, float]:
    """Quantise log-odds to int8 (``q = round(l / scale)``, ``scale = l_max / 127``) and
    base64 the bytes, row-major from the south-west corner. Returns ``(data, scale)``."""
    scale = l_max / 127.0
    q = np.clip(np.rint(log_odds / scale), -127, 127).astype(np.int8)
    return base64.b64encode(q.tobytes(order="C")).decode("ascii"), scale


def decode_log_odds(data: str, rows: int, cols: int, scale: float) -> FloatArray:
    """Inverse of :func:`encode_log_odds`: ``(rows, cols)`` log-odds, row 0 south."""
    q = np.frombuffer(base64.b64decode(data), dtype=np.int8)
    if q.size != rows * cols:
        raise EstimationError(f"occupancy data holds {q.size} cells, expected {rows}x{cols}")
    return q.reshape(rows, cols).astype(float) * scale


class OccupancyGrid:
    """A log-odds occupancy grid with its origin at world ``(0, 0)`` (south-west corner)."""

    def __init__(
        self, cols: int, rows: int, resolution_m: float, params: OccupancyParams
    ) -> None:
        if cols <= 0 or rows <= 0 or not resolution_m > 0:
            raise EstimationError("an occupancy grid needs cols, rows and resolution_m > 0")
        self.cols = cols
        self.rows = rows
        self.resolution_m = resolution_m
        self.params = params
        self.log_odds = np.zeros((rows, cols))
        self.observed = np.zeros((rows, cols), dtype=bool)

    @classmethod
    def for_world(cls, world: Grid, resolution_m: float, params: OccupancyParams) -> OccupancyGrid:
        """A grid covering the world's bounding box at ``resolution_m``."""
        cols = math.ceil(world.width_m / resolution_m - 1e-9)
        rows = math.ceil(world.height_m / resolution_m - 1e-9)
        return cls(cols, rows, resolution_m, params)

    def integrate(
        self, sensor_xy: tuple[float, float], phi: float, range_m: float, beam: BeamModel
    ) -> None:
        """Add one reading (sensor position and beam axis in the world frame)."""
        occ, free = beam_cells(
            (self.rows, self.cols), self.resolution_m, sensor_xy, phi, range_m, beam,
            self.params.mark_free_on_no_echo,
            self.params.free_margin_cells * self.resolution_m,
        )
        flat = self.log_odds.reshape(-1)
        if occ.size:
            flat[occ] += self.params.l_occ * min(1.0, self.params.occ_share_cells / occ.size)
        flat[free] += self.params.l_free
        seen = self.observed.reshape(-1)
        seen[occ] = True
        seen[free] = True
        np.clip(self.log_odds, self.params.l_min, self.params.l_max, out=self.log_odds)

    def integrate_scan(
        self,
        robot_pose: tuple[float, float, float],
        sensor_poses: ArrayLike,
        ranges: ArrayLike,
        beam: BeamModel,
    ) -> None:
        """Add one reading per sensor: ``sensor_poses`` ``(n, 3)`` body-frame ``[x, y, yaw]``
        (x forward, y left), ``ranges`` ``(n,)`` metres."""
        x, y, th = robot_pose
        c, s = math.cos(th), math.sin(th)
        poses = np.asarray(sensor_poses, dtype=float)
        rng = np.asarray(ranges, dtype=float)
        for (bx, by, yaw), d in zip(poses, rng, strict=True):
            self.integrate((x + c * bx - s * by, y + s * bx + c * by), th + yaw, float(d), beam)

    def probabilities(self) -> FloatArray:
        """``P(occupied)`` per cell, ``(rows, cols)``; 0.5 where nothing was observed."""
        return prob_from_log_odds(self.log_odds)

    def classify(self) -> IntArray:
        """Per cell: 1 occupied (log-odds > 0), 0 free (<= 0), -1 never observed."""
        return np.where(self.observed, (self.log_odds > 0).astype(np.int64), -1)

    def encode(self) -> tuple[str, float]:
        """``(base64 int8 log-odds, scale)``; see :func:`encode_log_odds`."""
        return encode_log_odds(self.log_odds, self.params.l_max)
