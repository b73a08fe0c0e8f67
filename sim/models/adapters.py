"""Glue between the simulator's sensor seams (``sim/sensors/base.py``) and the pure error models.

Each class here is a thin stateful wrapper: it holds the validated params (the sensor config's
``errors``), any per-run state (the gyro's bias), and implements ``measure(truth, variates)`` (or
``perturb`` for the drive) by calling the pure functions of ``sim/models/*`` -- their ``*_with``
forms, which take the variates drawn, or the compiled kernels directly -- with the same draws,
in the same order, as the pure ``measure`` functions the statistical tests hold. ``variates`` is
the sensor's :class:`sim.noise.BlockStream` in the simulator (any ``Generator`` also works).
:data:`ERROR_MODELS` maps sensor names to factories ``factory(config, rng)``, called by the
simulator at every reset.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np
from koala_bridge.sim.models import _kernels
from koala_bridge.sim.models import camera as camera_model
from koala_bridge.sim.models import compass as compass_model
from koala_bridge.sim.models import drive as drive_model
from koala_bridge.sim.models import gyro as gyro_model
from koala_bridge.sim.models import ir as ir_model
from koala_bridge.sim.models import sonar as sonar_model
from koala_bridge.sim.noise import BlockStream, LookupTable, Variates, rate_scaled_sigma
from koala_bridge.sim.robot import Motion, RobotState, arc_displacement
from koala_bridge.sim.sensors.base import fan_offsets
from koala_bridge.sim.sensors.camera import CameraTruth
from koala_bridge.sim.sensors.compass import CompassTruth
from koala_bridge.sim.sensors.gyro import GyroTruth
from koala_bridge.sim.sensors.ir import IrTruth
from koala_bridge.sim.sensors.sonar import SonarTruth
from koala_bridge.sim.types import (
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
        self.sigma = rate_scaled_sigma(params.drive_error, 1.0 / dt, params.reference_rate_hz)

    def perturb(self, ideal: Motion, state: RobotState, rng: Variates) -> Motion:
        if self.params.ideal:
            return ideal
        if isinstance(rng, BlockStream):
            eps = rng.normal_list(2)
            u = rng.uniform_list(2)
        else:
            eps = rng.standard_normal(2).tolist()
            u = rng.random(2).tolist()
        left, right = drive_model.perturb_wheel_steps_with(
            ideal.left_m, ideal.right_m, self.sigma, self.params, eps[0], eps[1], u[0], u[1],
            state.collided)
        dt = self.dt
        dx, dy, dth = arc_displacement(left / dt, right / dt, self.wheel_base_m, dt)
        return Motion(dx, dy, dth, ideal.left_m, ideal.right_m)


class IrError:
    def __init__(self, params: ir_model.IrErrorParams, response: LookupTable,
                 ray_offsets: np.ndarray, n_sensors: int) -> None:
        self.params = params
        self.response = response
        self.ray_offsets = ray_offsets
        self.weights = np.ascontiguousarray(ir_model.ray_weights(ray_offsets,
                                                                 params.gaussian_width))
        self.rho = np.full((n_sensors, ray_offsets.shape[0]), params.reflectivity)
        self.n = n_sensors
        self.n_draws = 0 if params.ideal else 3 * n_sensors
        self.constants = ir_model.kernel_constants(self.weights, self.rho, response, params)

    def measure(self, truth: IrTruth, rng: Variates) -> IrReading:
        # ir_model.measure_with, with the kernel's constant arguments computed once.
        z = np.asarray(rng.standard_normal(self.n_draws)) if self.n_draws else _NONE
        out = np.empty((3, self.n), dtype=np.int64)
        w, rho, rx, ry, ex, ey, fp, off = self.constants
        _kernels.ir_kernel(truth.ray_ranges, z, w, rho, rx, ry, ex, ey, fp, off, out)
        return IrReading(counts=out[0], ambient=out[1], truth_counts=out[2],
                         truth_ranges=truth.axis_ranges)


class SonarError:
    """The sonar model on the simulator's cast: one compiled call (second legs, crosstalk
    geometry, echoes, noise) with the variates of :func:`sim.models.sonar.measure` pre-drawn."""

    def __init__(self, params: sonar_model.SonarErrorParams, half_aperture_rad: float,
                 n_sensors: int, min_range_m: float, max_range_m: float) -> None:
        self.params = p = params
        self.half_aperture_rad = half_aperture_rad
        self.n = n_sensors
        self.cycle = sonar_model.same_cycle(n_sensors, p.firing_groups)
        self.use_cross = bool(p.crosstalk_probability > 0 and n_sensors > 1 and self.cycle.any())
        self.table_x = p.distance_error.x
        self.table_y = p.distance_error.y
        self.fp = np.array([max_range_m, min_range_m, math.radians(p.critical_angle_deg),
                            p.late_echo_probability, p.crosstalk_probability,
                            p.glitch_probability, p.min_range_m, half_aperture_rad])
        # The draws of sim.models.sonar.measure: 3 n uniforms and n normals, and n^2 uniforms
        # more when two sonars share a firing cycle (uniforms and normals are separate streams,
        # so the 3 n + n^2 uniforms are one contiguous draw).
        self.n_uniforms = 0 if p.ideal else 3 * n_sensors + (n_sensors ** 2 if self.use_cross
                                                              else 0)
        self.n_normals = 0 if p.ideal else n_sensors
        # ideal, use_leg (late echoes need the walls), use_cross
        self.flags = np.array([p.ideal, p.late_echo_probability > 0, self.use_cross],
                              dtype=np.int64)
        self.flags_no_walls = np.array([p.ideal, False, self.use_cross], dtype=np.int64)

    def measure(self, truth: SonarTruth, rng: Variates) -> SonarReading:
        n = truth.n
        flags = self.flags if truth.walls is not None else self.flags_no_walls
        u = np.asarray(rng.random(self.n_uniforms)) if self.n_uniforms else _NONE
        z = np.asarray(rng.standard_normal(self.n_normals)) if self.n_normals else _NONE
        seg = truth.walls.packed if truth.walls is not None else _NO_SEG
        out = np.empty((3, n))
        _kernels.sonar_ring_kernel(seg, truth.rays, truth.index, truth.start, n, truth.k, self.fp,
                                   flags, self.table_x, self.table_y, self.cycle, u, z, out)
        return SonarReading(ranges=out[0], truth_ranges=out[1], incidence=out[2])


class GyroError:
    def __init__(self, params: gyro_model.GyroErrorParams, rate_hz: float,
                 rng: np.random.Generator) -> None:
        self.params = params
        self.period = 1.0 / rate_hz
        self.bias = gyro_model.initial_state(params, rng).bias    # turn-on bias
        self._dt = self.period
        self._constants = gyro_model.step_constants(params, self.period)

    def measure(self, truth: GyroTruth, rng: Variates) -> GyroReading:
        if self.params.ideal:
            return GyroReading(yaw_rate=truth.yaw_rate, truth_yaw_rate=truth.yaw_rate)
        dt = truth.interval_s if truth.interval_s > 0 else self.period
        if dt != self._dt:
            self._dt = dt
            self._constants = gyro_model.step_constants(self.params, dt)
        z = rng.normal_list(3) if isinstance(rng, BlockStream) else rng.standard_normal(3).tolist()
        rate, self.bias = gyro_model.measure_with(truth.yaw_rate, self.bias, self.params,
                                                  self._constants, z[0], z[1], z[2])
        return GyroReading(yaw_rate=rate, truth_yaw_rate=truth.yaw_rate)


class CompassError:
    def __init__(self, params: compass_model.CompassErrorParams) -> None:
        self.params = params
        self.coeffs = compass_model.coefficients(params)

    def measure(self, truth: CompassTruth, rng: Variates) -> CompassReading:
        if self.params.ideal:
            return CompassReading(field_uT=truth.field_body_uT, truth_field_uT=truth.field_body_uT)
        n = rng.normal_list(3) if isinstance(rng, BlockStream) else rng.standard_normal(3).tolist()
        b = compass_model.measure_with(truth.field_body, truth.left_speed, truth.right_speed,
                                       self.coeffs, n)
        return CompassReading(field_uT=np.array(b), truth_field_uT=truth.field_body_uT)


class CameraError:
    def __init__(self, params: camera_model.CameraErrorParams) -> None:
        self.params = params
        self.fp = camera_model.kernel_constants(params)

    def measure(self, truth: CameraTruth, rng: Variates) -> CameraReading:
        # camera_model.measure on the truth's rows, with its draws (3 uniforms and 3 normals per
        # landmark in view).
        m = truth.rows.shape[0]
        if self.params.ideal or m == 0:
            return CameraReading(observations=truth.observations, truth=truth.observations)
        u = np.asarray(rng.random(3 * m))
        z = np.asarray(rng.standard_normal(3 * m))
        out = np.empty((m, 4))
        c = _kernels.camera_kernel(truth.rows, truth.all_ids, self.fp, u, z, out)
        measured = tuple(LandmarkObservation(int(i), r, b) for i, r, b, _s in
                         out[:c].tolist())
        return CameraReading(observations=measured, truth=truth.observations)


_NONE = np.zeros(0)
_NO_SEG = np.zeros((5, 0))


# ------------------------------------------------------------------------------ factories
def _drive(cfg: Any, rng: np.random.Generator) -> DriveError:
    # The drive model needs the wheel base and the step: its factory gets the whole SimConfig.
    return DriveError(cfg.robot.drive.errors, cfg.robot.wheel_base_m, cfg.sim.dt_s)


def _ir(cfg: Any, rng: np.random.Generator) -> IrError:
    # The response table is the IR core's ([sensors.ir] response_range_m -> response_counts).
    table = LookupTable(cfg.response_range_m, cfg.response_counts,
                        np.zeros(cfg.response_range_m.shape[0]))
    return IrError(cfg.errors, table, fan_offsets(cfg.rays, math.radians(cfg.aperture_deg)),
                   int(cfg.poses.shape[0]))


def _sonar(cfg: Any, rng: np.random.Generator) -> SonarError:
    return SonarError(cfg.errors, 0.5 * math.radians(cfg.aperture_deg), int(cfg.poses.shape[0]),
                      cfg.min_range_m, cfg.max_range_m)


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
