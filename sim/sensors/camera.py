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

Error model: ``sim/models/camera.py`` (its params, pure functions and
:class:`~koala_bridge.sim.models.camera.CameraErrorModel`); config section ``[sensors.camera]``,
typed here by :class:`CameraConfig` (its keys; the error model's keys beside them go to its params).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import numba
import numpy as np
from koala_bridge.core.raycast import SegmentSet, first_hit, wrap_angle_compiled
from koala_bridge.core.schema import Bool, NonNegative, Positive, section
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.robot import RobotState
from koala_bridge.sim.sections import Pose, empty_errors, range_limits, sensor_section
from koala_bridge.sim.sensors.base import ErrorModel
from koala_bridge.sim.types import CameraReading, LandmarkObservation
from koala_bridge.sim.world import World
from pydantic import Field

# A landmark on a wall is not hidden by that wall: the sight line stops this short of it.
LOS_TOLERANCE_M = 1e-9


@section
class CameraConfig:
    """``[sensors.camera]``: landmark observations within a field of view and line of sight."""

    rate_hz: Positive
    ideal: Bool
    pose: Pose                          # body frame [x, y, theta_rad]
    fov_deg: Annotated[Positive, Field(le=360)]   # full horizontal field of view
    min_range_m: NonNegative
    max_range_m: Positive
    errors: Any = field(default_factory=empty_errors)

    def __post_init__(self) -> None:
        range_limits(self.min_range_m, self.max_range_m, "sensors.camera")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraConfig:
        return sensor_section(cls, d, "sensors.camera", "camera")


@dataclass(frozen=True, eq=False)
class CameraTruth:
    observations: tuple[LandmarkObservation, ...]   # every landmark in view, true values
    rows: np.ndarray        # (v, 5) per observation: id, range, bearing, viewing angle, a_max
    all_ids: np.ndarray     # (L,) int64, every landmark id of the world

    @property
    def ids(self) -> np.ndarray:
        return self.rows[:, 0].astype(np.int64)

    @property
    def viewing_angle(self) -> np.ndarray:
        """(v,) rad, between the landmark's facing and the direction landmark -> camera."""
        return self.rows[:, 3]

    @property
    def a_max(self) -> np.ndarray:
        """(v,) rad, each landmark's full viewing cone."""
        return self.rows[:, 4]


@numba.njit(cache=True, nogil=True)
def visible_landmarks(
    landmarks: np.ndarray, seg: np.ndarray, cx: float, cy: float, theta: float, axis: float,
    min_range: float, max_range: float, cos_half_fov: float, out: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Landmarks ``(L, 5)`` rows ``[id, x, y, facing, a_max]`` seen from a camera at
    ``(cx, cy)`` whose axis points at ``axis`` (robot heading ``theta``): within range, within
    the field of view (by the dot product: ``v . a >= cos(fov / 2) |v|``) and not hidden by a
    wall (``seg``: :attr:`core.raycast.SegmentSet.packed`). Writes one row per visible landmark
    into ``out`` (L, 5): id, range, bearing (CCW from the heading), viewing angle (between the
    landmark's facing and the direction landmark -> camera), a_max; returns their number."""
    ax = math.cos(axis)
    ay = math.sin(axis)
    c = 0
    for i in range(landmarks.shape[0]):
        vx = landmarks[i, 1] - cx
        vy = landmarks[i, 2] - cy
        d = math.hypot(vx, vy)
        if not (min_range <= d <= max_range) or d == 0.0:
            continue
        if vx * ax + vy * ay < cos_half_fov * d:
            continue
        _t, wall, _inc = first_hit(seg, cx, cy, vx / d, vy / d, max(d - LOS_TOLERANCE_M, 0.0))
        if wall >= 0:
            continue
        direction = math.atan2(vy, vx)
        out[c, 0] = landmarks[i, 0]
        out[c, 1] = d
        out[c, 2] = wrap_angle_compiled(direction - theta)
        out[c, 3] = wrap_angle_compiled(direction + math.pi - landmarks[i, 3])
        out[c, 4] = landmarks[i, 4]
        c += 1
    return c


_NO_OBS: tuple[LandmarkObservation, ...] = ()
_NOTHING = CameraReading(_NO_OBS, _NO_OBS)


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
        self._lm = np.array([(lm.id, lm.x, lm.y, math.radians(lm.facing_deg),
                              math.radians(lm.a_max_deg)) for lm in lms], dtype=float
                            ).reshape(-1, 5)
        self.half_fov = math.radians(params.fov_deg) / 2.0
        # fov_deg = 360 -> cos(pi) = -1 accepts every direction.
        self._cos_half_fov = math.cos(self.half_fov) - 1e-12

    def _visible(self, state: RobotState) -> np.ndarray:
        p = self.params
        c, s = math.cos(state.theta), math.sin(state.theta)
        out = np.empty((self._lm.shape[0], 5))
        m = visible_landmarks(
            self._lm, self.walls.packed, state.x + c * p.pose[0] - s * p.pose[1],
            state.y + s * p.pose[0] + c * p.pose[1], state.theta, state.theta + p.pose[2],
            p.min_range_m, p.max_range_m, self._cos_half_fov, out)
        return out[:m]

    def truth(self, state: RobotState) -> CameraTruth:
        """The landmarks in view with what an error model needs (module docstring)."""
        return self._truth(self._visible(state))

    def _truth(self, vis: np.ndarray) -> CameraTruth:
        obs = tuple(LandmarkObservation(int(i), d, b) for i, d, b, _v, _a in vis.tolist())
        return CameraTruth(obs, vis, self._all_ids)

    def measure(self, state: RobotState, variates: Variates) -> CameraReading:
        vis = self._visible(state)
        if vis.shape[0] == 0:
            return _NOTHING         # nothing in view: no model draws anything either
        if self.error_model is None:
            obs = tuple(LandmarkObservation(int(i), d, b) for i, d, b, _v, _a in vis.tolist())
            return CameraReading(obs, obs)
        return self.error_model.measure(self._truth(vis), variates)
