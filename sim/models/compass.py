"""Magnetic compass: the robot's own disturbances (hard iron, soft iron, motor currents) and white
noise on top of the Earth field plus local sources (seeds/000 eq. 16–18).

Seed (seeds/000_b0d2d08e12d78625.txt, "Magnetic compass"): "The power of a magnetic field
vanishes inverse proportional to the squared distance"::

    F = 1 / d_MK^2 (in the direction L_M - L_K)          (16)
    F_tot = sum_i F_i                                     (17)–(18)
    "The influence of the north pole is just one of these force vectors, lets assume F_0."

Read: each source i contributes a horizontal vector of magnitude ``strength_i / d_i^2`` (strength
= field at 1 m, ``sim.world.MagneticSource``) pointing from the robot towards the source (the
extracted exponent ``2(L_M - L_K)`` is the unit direction vector fused into the power); the Earth
field is ``F_0``; the compass sees the vector sum. That noise-free part is the compass's truth,
computed by ``sim.sensors.compass.field_world`` (distances floored at ``min_source_distance_m``);
this module adds what the robot itself does to it.

Robot disturbances (beyond the seed; the standard magnetometer model of ArduPilot's compass
calibration / SITL ``SIM_MAG_*`` parameters)::

    B_m = S @ B_body + b_hard + M @ i + n,   n ~ N(0, noise_sigma_uT^2 I)

``S`` soft-iron matrix (3x3), ``b_hard`` hard-iron offset (uT, body FLU), ``M`` (3x2) field per
ampere of the left and right motor currents ``i``, the currents taken proportional to the wheel
speeds (``motor_current_A_per_mps``; a DC motor's current follows its load, and on a flat floor
the load grows with speed through friction; the sign flips with the direction of rotation).

The simulator's stateful model is :class:`CompassErrorModel` (end of this module; the truth it
perturbs comes from ``sim/sensors/compass.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). No compiled kernel: a 3-vector per step.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from koala_bridge.core.schema import (
    Bool,
    ConfigError,
    Finite,
    FloatTuple,
    NestedFloats,
    NonNegative,
    section,
)
from koala_bridge.sim.models._params import params_from_dict
from koala_bridge.sim.noise import BlockStream, Variates
from koala_bridge.sim.sensors.compass import CompassTruth
from koala_bridge.sim.types import CompassReading


def _identity() -> tuple[tuple[float, ...], ...]:
    return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@section
class CompassErrorParams:
    """``[sensors.compass]`` error-model keys. Field in microtesla, body frame FLU.

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that the sensor's section (sim/sensors/) owns and hands over.
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal",)
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({
        "hard_iron_uT": (0.0, 0.0, 0.0), "soft_iron": _identity(),
        "motor_uT_per_A": ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0)), "motor_current_A_per_mps": 0.0,
        "noise_sigma_uT": 0.0})

    ideal: Bool = False
    hard_iron_uT: FloatTuple = (4.0, -2.5, 1.0)
    soft_iron: NestedFloats = ((1.02, 0.01, 0.0), (0.01, 0.98, 0.0), (0.0, 0.0, 1.0))
    # rows x, y, z; columns left, right motor
    motor_uT_per_A: NestedFloats = ((0.8, -0.8), (0.5, 0.5), (0.3, 0.3))
    motor_current_A_per_mps: Finite = 1.0   # motor current per wheel speed
    noise_sigma_uT: NonNegative = 0.3

    def __post_init__(self) -> None:
        if np.shape(self.hard_iron_uT) != (3,):
            raise ConfigError("'hard_iron_uT' must have 3 components")
        if np.shape(self.soft_iron) != (3, 3):
            raise ConfigError("'soft_iron' must be a 3x3 matrix (3 rows of 3)")
        if np.shape(self.motor_uT_per_A) != (3, 2):
            raise ConfigError("'motor_uT_per_A' must be 3 rows [left, right] (uT per A)")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.compass") -> CompassErrorParams:
        return params_from_dict(cls, d, section)


def motor_currents_A(left_mps: float, right_mps: float, params: CompassErrorParams) -> np.ndarray:
    """Motor currents (A), proportional to wheel speed (see module doc)."""
    return params.motor_current_A_per_mps * np.array([left_mps, right_mps])


def measure(field_body_uT: np.ndarray, wheel_speeds_mps: tuple[float, float],
            params: CompassErrorParams, rng: Variates) -> np.ndarray:
    """Measured field (uT, body FLU) from the true one: ``S B + b_hard + M i + n``.
    Draws three normals per call (none when ideal)."""
    b = np.asarray(field_body_uT, dtype=float)
    if params.ideal:
        return b.copy()
    i = motor_currents_A(wheel_speeds_mps[0], wheel_speeds_mps[1], params)
    return (np.asarray(params.soft_iron) @ b + np.asarray(params.hard_iron_uT)
            + np.asarray(params.motor_uT_per_A) @ i
            + params.noise_sigma_uT * np.asarray(rng.standard_normal(3)))


def coefficients(params: CompassErrorParams) -> tuple[float, ...]:
    """The constants of :func:`measure_with`, flat: S (row-major), b_hard, M (row-major),
    motor_current_A_per_mps, noise_sigma_uT."""
    return (*(x for row in params.soft_iron for x in row), *params.hard_iron_uT,
            *(x for row in params.motor_uT_per_A for x in row), params.motor_current_A_per_mps,
            params.noise_sigma_uT)


def measure_with(b: Sequence[float], left_mps: float, right_mps: float,
                 coeffs: Sequence[float], n: Sequence[float]) -> tuple[float, float, float]:
    """:func:`measure` for one sample in scalar arithmetic: ``b`` the true field (3 floats),
    ``coeffs`` of :func:`coefficients`, ``n`` three standard normals. The simulator's path
    (numpy calls on 3-vectors cost more than the arithmetic)."""
    (s00, s01, s02, s10, s11, s12, s20, s21, s22, h0, h1, h2,
     m00, m01, m10, m11, m20, m21, k, sig) = coeffs
    bx, by, bz = b
    il = k * left_mps
    ir = k * right_mps
    return (s00 * bx + s01 * by + s02 * bz + h0 + m00 * il + m01 * ir + sig * n[0],
            s10 * bx + s11 * by + s12 * bz + h1 + m10 * il + m11 * ir + sig * n[1],
            s20 * bx + s21 * by + s22 * bz + h2 + m20 * il + m21 * ir + sig * n[2])


# ------------------------------------------------------------------ the simulator's model


class CompassErrorModel:
    """The stateful compass error model the simulator calls (``sim/sensors/compass.py`` seam):
    the params, the per-run state, and ``measure(truth, variates)`` built on the functions
    above, drawing the same variates in the same order as :func:`measure`."""

    def __init__(self, params: CompassErrorParams) -> None:
        self.params = params
        self.coeffs = coefficients(params)

    def measure(self, truth: CompassTruth, rng: Variates) -> CompassReading:
        if self.params.ideal:
            return CompassReading(field_uT=truth.field_body_uT, truth_field_uT=truth.field_body_uT)
        n = rng.normal_list(3) if isinstance(rng, BlockStream) else rng.standard_normal(3).tolist()
        b = measure_with(truth.field_body, truth.left_speed, truth.right_speed,
                                       self.coeffs, n)
        return CompassReading(field_uT=np.array(b), truth_field_uT=truth.field_body_uT)


def error_model(cfg: Any, rng: np.random.Generator) -> CompassErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``), called at every reset with the
    ``[sensors.compass]`` config and the sensor's own generator."""
    return CompassErrorModel(cfg.errors)
