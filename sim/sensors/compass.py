"""3-axis magnetometer: Earth field plus local magnetic sources, body frame FLU, microtesla.

Truth (pure, :func:`field_world` / :func:`field_body`), seeds/000 eq. 16-18: the field is the
vector sum of the Earth field ``F_0`` (``World.earth_field``) and one horizontal vector per local
source ``i`` of magnitude ``strength_i / d_i^2`` (``strength_uT`` is the field at 1 m; ``d_i``
clamped below at ``min_source_distance_m``), pointing from the robot towards the source (away for
a negative strength). The world-frame vector (x east, y north, z up) is rotated into the body frame
(x forward, y left, z up) by the robot's heading::

    b_x = cos(theta) B_x + sin(theta) B_y,   b_y = -sin(theta) B_x + cos(theta) B_y,   b_z = B_z

A level compass's heading, clockwise from magnetic north, is ``atan2(b_y, b_x)`` in FLU.

Seam: ``CompassSensor.measure(state, variates)``; an error model (issue 3: hard/soft iron,
motor-current disturbance) gets :class:`CompassTruth`, which includes the wheel speeds.

Error model: ``sim/models/compass.py`` (its params, pure functions and
:class:`~koala_bridge.sim.models.compass.CompassErrorModel`); config section ``[sensors.compass]``,
typed here by :class:`CompassConfig` (its keys; the error model's keys go to its params).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from koala_bridge.core.schema import Bool, Positive, section
from koala_bridge.sim.noise import Variates
from koala_bridge.sim.robot import RobotState
from koala_bridge.sim.sections import empty_errors, sensor_section
from koala_bridge.sim.sensors.base import ErrorModel
from koala_bridge.sim.types import CompassReading
from koala_bridge.sim.world import World


@section
class CompassConfig:
    """``[sensors.compass]``: 3-axis magnetometer, Earth field plus local sources (1/d^2)."""

    rate_hz: Positive
    ideal: Bool
    min_source_distance_m: Positive     # 1/d^2 is clamped at this distance (no singularity)
    errors: Any = field(default_factory=empty_errors)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CompassConfig:
        return sensor_section(cls, d, "sensors.compass", "compass")


@dataclass(frozen=True, slots=True, eq=False)
class CompassTruth:
    field_body_uT: np.ndarray                   # (3,) FLU
    field_body: tuple[float, float, float]      # the same as floats (scalar models)
    field_world_uT: tuple[float, float, float]  # x east, y north, z up
    theta: float
    left_speed: float             # m/s, for motor-current disturbances
    right_speed: float


def field_world(
    x: float,
    y: float,
    earth_uT: tuple[float, float, float],
    sources: tuple[tuple[float, float, float], ...],
    min_source_distance_m: float,
) -> tuple[float, float, float]:
    """World-frame field at ``(x, y)``: Earth ``(bx, by, bz)`` plus sources ``(sx, sy, strength)``.

    Scalar Python on purpose: worlds hold a handful of sources, and a loop over them is several
    times faster than numpy calls on arrays that small.
    """
    bx, by, bz = earth_uT
    for sx, sy, strength in sources:
        vx = sx - x
        vy = sy - y
        dist = math.hypot(vx, vy)
        if dist == 0.0:
            continue            # on top of the source: no direction (clamped magnitude undefined)
        d = max(dist, min_source_distance_m)
        k = strength / (d * d) / dist
        bx += k * vx
        by += k * vy
    return (bx, by, bz)


def field_body(b_world: tuple[float, float, float], theta: float
               ) -> tuple[float, float, float]:
    """Rotate a world-frame field into the body frame FLU (module docstring)."""
    c = math.cos(theta)
    s = math.sin(theta)
    return (c * b_world[0] + s * b_world[1], -s * b_world[0] + c * b_world[1], b_world[2])


class CompassSensor:
    name = "compass"

    def __init__(
        self,
        params: CompassConfig,
        world: World,
        error_model: ErrorModel[CompassTruth, CompassReading] | None = None,
    ) -> None:
        self.params = params
        self.error_model = None if params.ideal else error_model
        e = world.earth_field.vector_world()
        self.earth = (float(e[0]), float(e[1]), float(e[2]))
        self.sources = tuple((m.x, m.y, m.strength_uT) for m in world.magnetic_sources)

    def truth(self, state: RobotState) -> CompassTruth:
        bw = field_world(state.x, state.y, self.earth, self.sources,
                         self.params.min_source_distance_m)
        b = field_body(bw, state.theta)
        return CompassTruth(np.array(b), b, bw, state.theta, state.left_speed, state.right_speed)

    def measure(self, state: RobotState, variates: Variates) -> CompassReading:
        if self.error_model is None:
            bw = field_world(state.x, state.y, self.earth, self.sources,
                             self.params.min_source_distance_m)
            b = np.array(field_body(bw, state.theta))
            return CompassReading(b, b)
        return self.error_model.measure(self.truth(state), variates)
