"""Camera landmark observations: (id, range, bearing) of every landmark in view.

Truth (pure, :func:`camera_truth`): the camera sits at ``[sensors.camera] pose`` in the body frame.
A landmark is in view when its range from the camera lies within ``[min_range_m, max_range_m]``,
its direction lies within ``fov_deg / 2`` of the camera axis, and no wall crosses the line of sight
(:func:`sim.raycast.first_hit_before`). Range is measured from the camera; bearing is CCW from the
robot's heading (radians, wrapped to (-pi, pi]). Observations are ordered by landmark id.

Seam: ``CameraSensor.measure(state, rng)``; an error model (issue 3, seeds/000 eq. 5-14:
perception miss vs viewing angle and distance, recognition error, distance and angular errors)
gets :class:`CameraTruth`: the visible landmarks with, for each, the viewing angle (between the
landmark's facing direction and the direction from the landmark to the camera), its ``a_max``,
and the ids of all landmarks of the world (to draw a wrong id from).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.config import CameraConfig
from sim.raycast import SegmentSet, first_hit_before
from sim.robot import RobotState
from sim.sensors.base import ErrorModel
from sim.types import CameraReading, LandmarkObservation
from sim.world import World


@dataclass(frozen=True)
class CameraTruth:
    observations: tuple[LandmarkObservation, ...]   # every landmark in view, true values
    viewing_angle: np.ndarray                        # (v,) rad, per observation
    a_max: np.ndarray                                # (v,) rad, per observation
    all_ids: tuple[int, ...]                         # every landmark id of the world


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


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
        self.lx = np.array([lm.x for lm in lms], dtype=float)
        self.ly = np.array([lm.y for lm in lms], dtype=float)
        self.facing = np.radians([lm.facing_deg for lm in lms]).astype(float)
        self.a_max = np.radians([lm.a_max_deg for lm in lms]).astype(float)
        self.half_fov = math.radians(params.fov_deg) / 2.0

    def truth(self, state: RobotState) -> CameraTruth:
        p = self.params
        if not self.ids:
            return CameraTruth((), np.zeros(0), np.zeros(0), ())
        c, s = math.cos(state.theta), math.sin(state.theta)
        cx = state.x + c * p.pose[0] - s * p.pose[1]
        cy = state.y + s * p.pose[0] + c * p.pose[1]
        vx = self.lx - cx
        vy = self.ly - cy
        rng = np.hypot(vx, vy)
        bearing = _wrap(np.arctan2(vy, vx) - state.theta)
        off_axis = _wrap(bearing - p.pose[2])
        cand = (rng >= p.min_range_m) & (rng <= p.max_range_m) & (np.abs(off_axis) <= self.half_fov)
        idx = np.nonzero(cand)[0]
        if idx.size:
            n = idx.size
            blocked = first_hit_before(self.walls, np.full(n, cx), np.full(n, cy),
                                       self.lx[idx], self.ly[idx])
            idx = idx[~blocked]
        obs = tuple(LandmarkObservation(self.ids[i], float(rng[i]), float(bearing[i])) for i in idx)
        viewing = _wrap(np.arctan2(-vy[idx], -vx[idx]) - self.facing[idx])
        return CameraTruth(obs, viewing, self.a_max[idx], self.ids)

    def measure(self, state: RobotState, rng: np.random.Generator) -> CameraReading:
        truth = self.truth(state)
        if self.error_model is None:
            return CameraReading(truth.observations, truth.observations)
        return self.error_model.measure(truth, rng)
