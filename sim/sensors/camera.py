"""Camera landmark observations: (id, range, bearing) of every landmark in view.

Truth (pure): the camera sits at ``[sensors.camera] pose`` in the body frame. A landmark is in view
when its range from the camera lies within ``[min_range_m, max_range_m]``, its direction lies
within ``fov_deg / 2`` of the camera axis, and no wall crosses the line of sight. Range is
measured from the camera; bearing is CCW from the robot's heading (radians, wrapped to
(-pi, pi]). Observations are ordered by landmark id.

Two steps, so that the simulator can put the line-of-sight rays into the same ray cast as the
range sensors: :meth:`CameraSensor.candidates` (field of view and range, scalar Python: worlds
hold few landmarks) returns :class:`CameraCandidates` with one line-of-sight ray per candidate;
:meth:`CameraSensor.measure_from` takes which of them a wall blocks. :meth:`CameraSensor.measure`
does both with its own cast.

Seam: with ``ideal = false`` an error model (issue 3, seeds/000 eq. 5-14: perception miss vs
viewing angle and distance, recognition error, distance and angular errors) gets
:class:`CameraTruth`: the visible landmarks with, for each, the viewing angle (between the
landmark's facing direction and the direction from the landmark to the camera), its ``a_max``,
and the ids of all landmarks of the world (to draw a wrong id from).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.config import CameraConfig
from sim.raycast import SegmentSet, cast_rays
from sim.robot import RobotState, wrap_angle
from sim.sensors.base import ErrorModel
from sim.types import CameraReading, LandmarkObservation
from sim.world import World

# A landmark on a wall is not hidden by that wall: the sight line stops this short of it.
LOS_TOLERANCE_M = 1e-9


@dataclass(frozen=True)
class CameraTruth:
    observations: tuple[LandmarkObservation, ...]   # every landmark in view, true values
    viewing_angle: np.ndarray                        # (v,) rad, per observation
    a_max: np.ndarray                                # (v,) rad, per observation
    all_ids: tuple[int, ...]                         # every landmark id of the world


@dataclass(frozen=True)
class CameraCandidates:
    """Landmarks within range and field of view, before the line-of-sight test."""

    index: tuple[int, ...]          # into the sensor's landmark list (sorted by id)
    range: tuple[float, ...]
    bearing: tuple[float, ...]
    viewing: tuple[float, ...]
    ox: np.ndarray                  # (c,) line-of-sight rays: camera -> landmark
    oy: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    max_range: np.ndarray


_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False
_NO_CANDIDATES = CameraCandidates((), (), (), (), _EMPTY, _EMPTY, _EMPTY, _EMPTY, _EMPTY)


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
        self.landmarks = tuple((lm.x, lm.y, math.radians(lm.facing_deg),
                                math.radians(lm.a_max_deg)) for lm in lms)
        self.half_fov = math.radians(params.fov_deg) / 2.0
        # fov_deg = 360 -> cos(pi) = -1 accepts every direction.
        self._cos_half_fov = math.cos(self.half_fov) - 1e-12

    def candidates(self, state: RobotState) -> CameraCandidates:
        p = self.params
        c, s = math.cos(state.theta), math.sin(state.theta)
        cx = state.x + c * p.pose[0] - s * p.pose[1]
        cy = state.y + s * p.pose[0] + c * p.pose[1]
        idx: list[int] = []
        rngs: list[float] = []
        bearings: list[float] = []
        viewing: list[float] = []
        dxs: list[float] = []
        dys: list[float] = []
        axis = state.theta + p.pose[2]
        ax, ay = math.cos(axis), math.sin(axis)
        for i, (lx, ly, facing, _a_max) in enumerate(self.landmarks):
            vx = lx - cx
            vy = ly - cy
            d = math.hypot(vx, vy)
            if not (p.min_range_m <= d <= p.max_range_m) or d == 0.0:
                continue
            # Within the field of view: angle to the camera axis <= half_fov, by the dot product
            # (cheaper than atan2 + wrap for the landmarks that are rejected).
            if vx * ax + vy * ay < self._cos_half_fov * d:
                continue
            direction = math.atan2(vy, vx)
            idx.append(i)
            rngs.append(d)
            bearings.append(wrap_angle(direction - state.theta))
            viewing.append(wrap_angle(direction + math.pi - facing))
            dxs.append(vx / d)
            dys.append(vy / d)
        n = len(idx)
        if n == 0:
            return _NO_CANDIDATES
        return CameraCandidates(
            tuple(idx), tuple(rngs), tuple(bearings), tuple(viewing),
            np.full(n, cx), np.full(n, cy), np.array(dxs), np.array(dys),
            np.array(rngs) - LOS_TOLERANCE_M,
        )

    def truth_from(self, cand: CameraCandidates, blocked: np.ndarray) -> CameraTruth:
        if not cand.index:
            return CameraTruth((), _EMPTY, _EMPTY, self.ids)
        obs = []
        viewing = []
        a_max = []
        for j, i in enumerate(cand.index):
            if blocked[j]:
                continue
            obs.append(LandmarkObservation(self.ids[i], cand.range[j], cand.bearing[j]))
            viewing.append(cand.viewing[j])
            a_max.append(self.landmarks[i][3])
        return CameraTruth(tuple(obs), np.array(viewing), np.array(a_max), self.ids)

    def measure_from(
        self, cand: CameraCandidates, blocked: np.ndarray, rng: np.random.Generator
    ) -> CameraReading:
        """Reading given which candidates' lines of sight a wall blocks (``(c,)`` bool)."""
        truth = self.truth_from(cand, blocked)
        if self.error_model is None:
            return CameraReading(truth.observations, truth.observations)
        return self.error_model.measure(truth, rng)

    def measure(self, state: RobotState, rng: np.random.Generator) -> CameraReading:
        cand = self.candidates(state)
        if cand.index:
            hits = cast_rays(self.walls, cand.ox, cand.oy, cand.dx, cand.dy, cand.max_range)
            blocked = hits.index >= 0
        else:
            blocked = _EMPTY.astype(bool)
        return self.measure_from(cand, blocked, rng)
