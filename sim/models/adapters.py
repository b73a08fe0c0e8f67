"""Glue between the simulator's sensor seams (``sim/sensors/base.py``) and the pure error models.

Each class here is a thin stateful wrapper: it holds the validated params (the sensor config's
``errors``), any per-run state (the gyro's bias), and implements ``measure(truth, rng)`` (or
``perturb`` for the drive) by calling the pure functions of ``sim/models/*``. :data:`ERROR_MODELS`
maps sensor names to factories ``factory(config, rng)``, called by the simulator at every reset.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

from sim.models import _kernels
from sim.models import camera as camera_model
from sim.models import compass as compass_model
from sim.models import drive as drive_model
from sim.models import gyro as gyro_model
from sim.models import ir as ir_model
from sim.models import sonar as sonar_model
from sim.noise import LookupTable
from sim.robot import Motion, RobotState, arc_motion
from sim.sensors.base import fan_offsets
from sim.sensors.camera import CameraTruth
from sim.sensors.compass import CompassTruth
from sim.sensors.gyro import GyroTruth
from sim.sensors.ir import IrTruth
from sim.sensors.sonar import SonarTruth
from sim.types import (
    CameraReading,
    CompassReading,
    GyroReading,
    IrReading,
    LandmarkObservation,
    SonarReading,
)


class DriveError:
    """seeds/000 eq. 1–4 per wheel plus wall slip; implements ``sim.robot.DriveErrorModel``.

    The truth pose moves by the perturbed wheel steps; the motion's wheel travel (what the
    encoders count) stays the commanded one.
    """

    def __init__(self, params: drive_model.DriveErrorParams, wheel_base_m: float, dt: float
                 ) -> None:
        self.params = params
        self.wheel_base_m = wheel_base_m
        self.dt = dt

    def perturb(self, ideal: Motion, state: RobotState, rng: np.random.Generator) -> Motion:
        left, right = drive_model.perturb_wheel_steps(
            ideal.left_m, ideal.right_m, 1.0 / self.dt, self.params, rng,
            in_contact=state.collided,
        )
        real = arc_motion(left / self.dt, right / self.dt, self.wheel_base_m, self.dt)
        return Motion(real.dx_b, real.dy_b, real.dtheta, ideal.left_m, ideal.right_m)


class IrError:
    def __init__(self, params: ir_model.IrErrorParams, response: LookupTable,
                 ray_offsets: np.ndarray) -> None:
        self.params = params
        self.response = response
        self.ray_offsets = ray_offsets
        self.weights = ir_model.ray_weights(ray_offsets, params.gaussian_width)

    def measure(self, truth: IrTruth, rng: np.random.Generator) -> IrReading:
        counts, ambient, truth_counts = ir_model.measure(
            truth.ray_ranges, self.ray_offsets, self.response, self.params, rng,
            weights=self.weights)
        return IrReading(counts=counts, ambient=ambient, truth_counts=truth_counts,
                         truth_ranges=truth.axis_ranges)


class SonarError:
    def __init__(self, params: sonar_model.SonarErrorParams, half_aperture_rad: float) -> None:
        self.params = params
        self.half_aperture_rad = half_aperture_rad

    def measure(self, truth: SonarTruth, rng: np.random.Generator) -> SonarReading:
        p = self.params
        geo: dict[str, Any] = {}
        rays = truth.world_rays
        if rays is not None:
            ox, oy, dx, dy = (np.ascontiguousarray(a, dtype=float) for a in rays)   # (n, k)
            rr = truth.ray_ranges
            n, k = rr.shape
            if (p.crosstalk_probability > 0 and n > 1
                    and sonar_model.same_cycle(n, p.firing_groups).any()):
                r0 = np.where(np.isfinite(rr), rr, 0.0)
                geo["hit_xy"] = np.stack([ox + dx * r0, oy + dy * r0], axis=-1)
                geo["sensor_xy"] = np.stack([ox[:, k // 2], oy[:, k // 2]], axis=-1)
                geo["sensor_heading"] = np.arctan2(dy[:, k // 2], dx[:, k // 2])
            if truth.walls is not None and p.late_echo_probability > 0:
                # Specular path first hit -> second surface -> sensor, per ray (inf: none).
                leg = np.empty(n * k)
                _kernels.second_leg_kernel(
                    truth.walls.packed, ox.ravel(), oy.ravel(), dx.ravel(), dy.ravel(),
                    np.ascontiguousarray(rr, dtype=float).ravel(),
                    np.ascontiguousarray(truth.ray_wall, dtype=np.intp).ravel(),
                    truth.max_range_m, leg)
                geo["second_leg_m"] = leg.reshape(n, k)
        m = sonar_model.measure(truth.ray_ranges, truth.ray_incidence, truth.max_range_m,
                                p, rng, half_aperture_rad=self.half_aperture_rad, **geo)
        ranges = np.where(m.ranges < truth.min_range_m, 0.0, m.ranges)   # the Koala reads 0
        return SonarReading(ranges=ranges, truth_ranges=truth.ranges, incidence=truth.incidence)


class GyroError:
    def __init__(self, params: gyro_model.GyroErrorParams, rate_hz: float,
                 rng: np.random.Generator) -> None:
        self.params = params
        self.period = 1.0 / rate_hz
        self.state = gyro_model.initial_state(params, rng)    # turn-on bias

    def measure(self, truth: GyroTruth, rng: np.random.Generator) -> GyroReading:
        dt = truth.interval_s if truth.interval_s > 0 else self.period
        rate, self.state = gyro_model.measure(truth.yaw_rate, dt, self.state, self.params, rng)
        return GyroReading(yaw_rate=rate, truth_yaw_rate=truth.yaw_rate)


class CompassError:
    def __init__(self, params: compass_model.CompassErrorParams) -> None:
        self.params = params

    def measure(self, truth: CompassTruth, rng: np.random.Generator) -> CompassReading:
        b = compass_model.measure(truth.field_body_uT, (truth.left_speed, truth.right_speed),
                                  self.params, rng)
        return CompassReading(field_uT=b, truth_field_uT=truth.field_body_uT)


class CameraError:
    def __init__(self, params: camera_model.CameraErrorParams) -> None:
        self.params = params

    def measure(self, truth: CameraTruth, rng: np.random.Generator) -> CameraReading:
        obs = truth.observations
        m = camera_model.measure(
            np.array([o.id for o in obs], dtype=int),
            np.array([o.range for o in obs], dtype=float),
            np.array([o.bearing for o in obs], dtype=float),
            truth.viewing_angle, truth.a_max, np.array(truth.all_ids, dtype=int),
            self.params, rng,
        )
        measured = tuple(LandmarkObservation(int(i), float(r), float(b))
                         for i, r, b in zip(m.ids, m.ranges, m.bearings, strict=True))
        return CameraReading(observations=measured, truth=obs)


# ------------------------------------------------------------------------------ factories
def _drive(cfg: Any, rng: np.random.Generator) -> DriveError:
    # The drive model needs the wheel base and the step: its factory gets the whole SimConfig.
    return DriveError(cfg.robot.drive.errors, cfg.robot.wheel_base_m, cfg.sim.dt_s)


def _ir(cfg: Any, rng: np.random.Generator) -> IrError:
    table = LookupTable.from_rows(
        np.stack([cfg.response_range_m, cfg.response_counts], axis=1).tolist(), "sensors.ir")
    return IrError(cfg.errors, table, fan_offsets(cfg.rays, math.radians(cfg.aperture_deg)))


def _sonar(cfg: Any, rng: np.random.Generator) -> SonarError:
    return SonarError(cfg.errors, 0.5 * math.radians(cfg.aperture_deg))


def _gyro(cfg: Any, rng: np.random.Generator) -> GyroError:
    return GyroError(cfg.errors, cfg.rate_hz, rng)


def _compass(cfg: Any, rng: np.random.Generator) -> CompassError:
    return CompassError(cfg.errors)


def _camera(cfg: Any, rng: np.random.Generator) -> CameraError:
    return CameraError(cfg.errors)


ERROR_MODELS: Mapping[str, Any] = MappingProxyType({
    "drive": _drive,
    "ir": _ir,
    "sonar": _sonar,
    "gyro": _gyro,
    "compass": _compass,
    "camera": _camera,
})
