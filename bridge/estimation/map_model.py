"""Range sensors against the known map: expected ranges with their Jacobians (for the pose EKF)
and a likelihood field (for the particle relocaliser).

Both read the walls of the map the robot is given (:class:`koala_bridge.core.grid.Grid`): the
estimator knows the map, never the robot's true pose.

**Expected range of a ray** (the EKF's measurement model). A range sensor at body-frame pose
``(b_x, b_y, yaw)`` on a robot at ``(x, y, theta)`` casts from ``o = p + R(theta) b`` along
``d = (cos phi, sin phi)``, ``phi = theta + yaw``. When it hits the wall whose line is
``n . q = c`` (``n`` the unit normal), the range is ``r = (c - n . o) / (n . d)``, and::

    dr/dx = -n_x / (n . d)          dr/dy = -n_y / (n . d)
    dr/dtheta = -(n . do/dtheta + r n . dd/dtheta) / (n . d)
    do/dtheta = (-(s b_x + c b_y), c b_x - s b_y),   dd/dtheta = (-sin phi, cos phi)

(``c, s`` = cos, sin of ``theta``). This is the ray model of Thrun, Burgard and Fox,
*Probabilistic Robotics* (2005) §6.3, linearised. A ray whose hit point lies within
``corner_margin_m`` of a wall's end is not used: there the range jumps (or its slope does) under a
small change of pose, and no linearisation holds. A sensor with a beam (the sonar's 22.9 deg) is
modelled as the seed does it (seeds/004 "Sensor Models": Webots' sonar reading is the nearest hit
of ``rays`` rays spread over the aperture, rays beyond the critical incidence being lost): the
nearest direct hit among the beam's rays names the wall, and when that wall's normal lies
inside the beam the expected range is the perpendicular distance to it (the continuous cone's
first echo; the rays are its samples), whose derivative with respect to the heading comes only
from the sensor's offset from the robot's centre; a wall seen only obliquely is not used.

**Likelihood field** (Thrun et al. §6.4): a reading ``r`` of a sensor puts an obstacle at the end
point of its ray; the field is the distance from each point of the map to the nearest wall (a
Euclidean distance transform, ``scipy.ndimage.distance_transform_edt``, at ``resolution_m``), so the
likelihood of a reading is a Gaussian of the end point's distance, cheap enough to weigh
thousands of particles per reading. ``clearance`` is the same field read at the robot's centre:
a pose whose body would overlap a wall is not a pose the robot can be in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.grid import Grid
from koala_bridge.core.raycast import SegmentSet, cast_fan_arrays, point_segment_distances
from numpy.typing import NDArray
from scipy import ndimage

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RangeHit:
    """One usable expected range: sensor ``index``, range ``r`` (m) and ``H`` = dr/d(x, y,
    theta)."""

    index: int
    r: float
    H: tuple[float, float, float]


class MapModel:
    """The known map's walls, prepared for expected ranges and the likelihood field.

    Args:
        world: the map (its ``segments``, width and height).
        resolution_m: cell size of the distance field.
        corner_margin_m: rays hitting this close to a wall's end are not used.
    """

    def __init__(self, world: Grid, resolution_m: float = 0.01,
                 corner_margin_m: float = 0.03) -> None:
        self.world = world
        self.walls = SegmentSet.from_segments(world.segments)
        seg = self.walls.segments
        ex, ey = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
        length = np.hypot(ex, ey)
        self._normal = np.stack([-ey / length, ex / length], axis=1)          # (M, 2) unit
        self._offset = self._normal[:, 0] * seg[:, 0] + self._normal[:, 1] * seg[:, 1]
        self._margin_u = corner_margin_m / length                              # (M,)
        self.resolution_m = resolution_m
        self._field = self._distance_field(resolution_m)
        self._rows, self._cols = self._field.shape

    # -- the EKF's model ----------------------------------------------------------------

    def expected(self, pose: tuple[float, float, float], body: FloatArray,
                 max_range: FloatArray, beams: int = 1,
                 critical_incidence: float = math.pi / 2) -> list[RangeHit | None]:
        """Expected range and Jacobian of each sensor.

        Args:
            pose: ``(x, y, theta)`` of the robot.
            body: ``(3, S * beams)`` C-contiguous rays, body frame ``[x, y, angle]``: sensor ``i``
                owns columns ``i * beams .. (i + 1) * beams - 1``.
            max_range: ``(S * beams,)`` ranges beyond which nothing is seen.
            beams: rays per sensor; the sensor's expected range is the nearest of its rays that
                hits within ``critical_incidence`` (sonar: seeds/004 specular loss).
            critical_incidence: rad.

        Returns:
            per sensor, a :class:`RangeHit` (``r = inf`` when nothing is within its range), or
            None when the hit is near a wall's end or every ray that hits is beyond the critical
            incidence (module docstring).
        """
        x, y, th = pose
        out, index = cast_fan_arrays(self.walls, body, max_range, x, y, th)
        rng, inc = out[4], out[5]
        n_sensors = body.shape[1] // beams
        hits: list[RangeHit | None] = []
        c, s = math.cos(th), math.sin(th)
        for i in range(n_sensors):
            best, seen = -1, False
            for k in range(i * beams, (i + 1) * beams):
                if index[k] >= 0:
                    seen = True
                    if inc[k] <= critical_incidence and (best < 0 or rng[k] < rng[best]):
                        best = k
            if best < 0:  # nothing in range (r = inf), or only glancing hits (no echo known)
                hits.append(None if seen else RangeHit(i, math.inf, (0.0, 0.0, 0.0)))
                continue
            m = int(index[best])
            r = float(rng[best])
            ox, oy, dx, dy = out[0, best], out[1, best], out[2, best], out[3, best]
            seg = self.walls.segments[m]
            ex, ey = seg[2] - seg[0], seg[3] - seg[1]
            u = ((ox + r * dx - seg[0]) * ex + (oy + r * dy - seg[1]) * ey) / (ex * ex + ey * ey)
            mu = self._margin_u[m]
            if u < mu or u > 1.0 - mu:
                hits.append(None)
                continue
            nx, ny = self._normal[m]
            nd = nx * dx + ny * dy
            if abs(nd) < 1e-6:
                hits.append(None)
                continue
            bx, by = body[0, best], body[1, best]
            do_x, do_y = -(s * bx + c * by), c * bx - s * by
            if beams > 1:
                hits.append(self._beam_hit(i, m, ox, oy, do_x, do_y, th, body,
                                           range(i * beams, (i + 1) * beams)))
                continue
            dd_x, dd_y = -dy, dx
            h_th = -(nx * do_x + ny * do_y + r * (nx * dd_x + ny * dd_y)) / nd
            hits.append(RangeHit(i, r, (-nx / nd, -ny / nd, h_th)))
        return hits

    def _beam_hit(self, i: int, m: int, ox: float, oy: float, do_x: float, do_y: float,
                  th: float, body: FloatArray, cols: range) -> RangeHit | None:
        """A beam's first echo off wall ``m``: when the wall's normal lies inside the beam, the
        echo comes from the foot of the perpendicular, so the range is the distance to the
        wall's line and does not depend on the heading except through the sensor's offset
        (the continuous cone of which the rays are samples; the nearest of a few rays would
        turn every sweep of the beam across the wall into false heading information)."""
        nx, ny = self._normal[m]
        a, b = self.walls.segments[m, :2]
        dist = (ox - a) * nx + (oy - b) * ny          # signed, + on the normal's side
        if dist < 0:
            nx, ny, dist = -nx, -ny, -dist
        # direction from the sensor to the wall: -n; is it inside the beam?
        angles = body[2, cols.start:cols.stop]
        axis = th + 0.5 * (float(angles[0]) + float(angles[-1]))
        half = 0.5 * (float(angles[-1]) - float(angles[0]))
        off = math.atan2(-ny, -nx) - axis
        off = math.atan2(math.sin(off), math.cos(off))
        if abs(off) > half:
            return None
        # the foot of the perpendicular must lie on the wall, away from its ends
        seg = self.walls.segments[m]
        fx, fy = ox - dist * nx, oy - dist * ny
        ex, ey = seg[2] - seg[0], seg[3] - seg[1]
        u = ((fx - seg[0]) * ex + (fy - seg[1]) * ey) / (ex * ex + ey * ey)
        mu = self._margin_u[m]
        if u < mu or u > 1.0 - mu:
            return None
        return RangeHit(i, dist, (nx, ny, nx * do_x + ny * do_y))

    # -- the likelihood field -------------------------------------------------------------

    def _distance_field(self, res: float) -> FloatArray:
        w, h = self.world.width_m, self.world.height_m
        cols, rows = int(math.ceil(w / res)) + 1, int(math.ceil(h / res)) + 1
        free = np.ones((rows, cols), dtype=bool)
        for x0, y0, x1, y1 in self.walls.segments:
            n = int(math.ceil(math.hypot(x1 - x0, y1 - y0) / (0.5 * res))) + 1
            xs, ys = np.linspace(x0, x1, n), np.linspace(y0, y1, n)
            ci = np.clip(np.rint(xs / res).astype(int), 0, cols - 1)
            ri = np.clip(np.rint(ys / res).astype(int), 0, rows - 1)
            free[ri, ci] = False
        # blocked cells are solid: every point inside is "in a wall"
        for col, row in self.world.blocked:
            c = self.world.cell_m
            r0, r1 = int(round(row * c / res)), int(round((row + 1) * c / res))
            c0, c1 = int(round(col * c / res)), int(round((col + 1) * c / res))
            free[r0:r1 + 1, c0:c1 + 1] = False
        return ndimage.distance_transform_edt(free) * res

    def distance(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Distance (m) from each point to the nearest wall; points outside the map are at the
        distance of the nearest map edge point plus how far outside they are."""
        res = self.resolution_m
        ci = np.rint(np.asarray(x) / res).astype(int)
        ri = np.rint(np.asarray(y) / res).astype(int)
        cc = np.clip(ci, 0, self._cols - 1)
        rc = np.clip(ri, 0, self._rows - 1)
        outside = np.hypot(ci - cc, ri - rc) * res
        return self._field[rc, cc] + outside

    def clearance(self, x: float, y: float) -> float:
        """:meth:`distance` of one point, without arrays (the estimator asks every step);
        ``-1`` outside the map."""
        if not (0.0 <= x <= self.world.width_m and 0.0 <= y <= self.world.height_m):
            return -1.0
        res = self.resolution_m
        col = min(int(x / res + 0.5), self._cols - 1)
        row = min(int(y / res + 0.5), self._rows - 1)
        return float(self._field[row, col])

    def nearest_wall(self, x: float, y: float) -> tuple[float, float, float]:
        """Exact distance (m) from ``(x, y)`` to the nearest wall segment and the unit direction
        from that wall's nearest point to ``(x, y)`` (no rasterisation: what contact tests
        need at millimetres)."""
        d = point_segment_distances(self.walls, x, y)
        m = int(np.argmin(d))
        seg = self.walls.segments[m]
        ex, ey = seg[2] - seg[0], seg[3] - seg[1]
        u = min(max(((x - seg[0]) * ex + (y - seg[1]) * ey) / (ex * ex + ey * ey), 0.0), 1.0)
        dx, dy = x - (seg[0] + u * ex), y - (seg[1] + u * ey)
        dist = float(d[m])
        return (dist, dx / dist, dy / dist) if dist > 0 else (0.0, 0.0, 0.0)

    def inside(self, x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        """Whether each point lies inside the map's outer bounds."""
        return (x >= 0) & (y >= 0) & (x <= self.world.width_m) & (y <= self.world.height_m)
