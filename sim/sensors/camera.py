"""Camera landmark observations: (id, range, bearing) of every landmark in view.

Truth (pure, :func:`visible_landmarks`): the camera sits at ``[sensors.camera] pose`` in the body
frame. A landmark is in view when its range from the camera lies within
``[min_range_m, max_range_m]``, its direction lies within ``fov_deg / 2`` of the camera axis, and
no wall crosses the line of sight. Range is measured from the camera; bearing is CCW from the
robot's heading (radians, wrapped to (-pi, pi]). Observations are ordered by landmark id.

Seam: with ``ideal = false`` an error model (seeds/000 eq. 5-14: perception miss vs viewing angle
and distance, recognition error, distance and angular errors; ``sim/models/camera.py``) gets
:class:`CameraTruth`: the visible landmarks with, for each, the viewing angle (between the
landmark's facing direction and the direction from the landmark to the camera), its ``a_max``,
and the ids of all landmarks of the world (to draw a wrong id from).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from sim.config import CameraConfig
from sim.noise import Variates
from sim.raycast import SegmentSet, first_hit
from sim.robot import RobotState, wrap_angle
from sim.sensors.base import ErrorModel
from sim.types import CameraReading, LandmarkObservation
from sim.world import World

# A landmark on a wall is not hidden by that wall: the sight line stops this short of it.
LOS_TOLERANCE_M = 1e-9


@dataclass(frozen=True, eq=False)
class CameraTruth:
    observations: tuple[LandmarkObservation, ...]   # every landmark in view, true values
    ids: np.ndarray                                  # (v,) int64, per observation
    ranges: np.ndarray                               # (v,) m
    bearings: np.ndarray                             # (v,) rad
    viewing_angle: np.ndarray                        # (v,) rad, per observation
    a_max: np.ndarray                                # (v,) rad, per observation
    all_ids: np.ndarray                              # (L,) int64, every landmark id of the world


@numba.njit(cache=True, nogil=True)
def visible_landmarks(
    landmarks: np.ndarray, seg: np.ndarray, cx: float, cy: float, ax: float, ay: float,
    min_range: float, max_range: float, cos_half_fov: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Landmarks ``(L, 4)`` rows ``[x, y, facing, a_max]`` seen from a camera at ``(cx, cy)``
    with unit axis ``(ax, ay)``: within range, within the field of view (by the dot product:
    ``v . a >= cos(fov / 2) |v|``) and not hidden by a wall (``seg``:
    :attr:`sim.raycast.SegmentSet.packed`). Returns their row indices, ranges and world-frame
    directions (rad)."""
    m = landmarks.shape[0]
    idx = np.empty(m, dtype=np.int64)
    rng = np.empty(m)
    direction = np.empty(m)
    c = 0
    for i in range(m):
        vx = landmarks[i, 0] - cx
        vy = landmarks[i, 1] - cy
        d = math.hypot(vx, vy)
        if not (min_range <= d <= max_range) or d == 0.0:
            continue
        if vx * ax + vy * ay < cos_half_fov * d:
            continue
        _t, wall, _inc = first_hit(seg, cx, cy, vx / d, vy / d, max(d - 1e-9, 0.0))
        if wall >= 0:
            continue
        idx[c] = i
        rng[c] = d
        direction[c] = math.atan2(vy, vx)
        c += 1
    return idx[:c], rng[:c], direction[:c]


class CameraSensor:
    name = "camera"

    def __init__(
        self,
        params: CameraConfig,
        world: World,
        walls: SegmentSet,
        error_model: ErrorModel[CameraTruth, CameraReading] | None = None,
    ) -> None:
        self.params = params
        self.error_model = None if params.ideal else error_model
        self.walls = walls
        lms = sorted(world.landmarks, key=lambda lm: lm.id)
        self.ids = tuple(lm.id for lm in lms)
        self._all_ids = np.array(self.ids, dtype=np.int64)
        self.landmarks = tuple((lm.x, lm.y, math.radians(lm.facing_deg),
                                math.radians(lm.a_max_deg)) for lm in lms)
        self._lm = np.array(self.landmarks, dtype=float).reshape(-1, 4)
        self.half_fov = math.radians(params.fov_deg) / 2.0
        # fov_deg = 360 -> cos(pi) = -1 accepts every direction.
        self._cos_half_fov = math.cos(self.half_fov) - 1e-12

    def truth(self, state: RobotState) -> CameraTruth:
        p = self.params
        c, s = math.cos(state.theta), math.sin(state.theta)
        cx = state.x + c * p.pose[0] - s * p.pose[1]
        cy = state.y + s * p.pose[0] + c * p.pose[1]
        axis = state.theta + p.pose[2]
        idx, rng, direction = visible_landmarks(
            self._lm, self.walls.packed, cx, cy, math.cos(axis), math.sin(axis), p.min_range_m,
            p.max_range_m, self._cos_half_fov)
        obs = []
        bearings = []
        viewing = []
        for i, d, a in zip(idx.tolist(), rng.tolist(), direction.tolist(), strict=True):
            b = wrap_angle(a - state.theta)
            obs.append(LandmarkObservation(self.ids[i], d, b))
            bearings.append(b)
            viewing.append(wrap_angle(a + math.pi - self.landmarks[i][2]))
        return CameraTruth(tuple(obs), self._all_ids[idx], rng, np.array(bearings),
                           np.array(viewing), self._lm[idx, 3], self._all_ids)

    def measure(self, state: RobotState, variates: Variates) -> CameraReading:
        truth = self.truth(state)
        if self.error_model is None:
            return CameraReading(truth.observations, truth.observations)
        return self.error_model.measure(truth, variates)
