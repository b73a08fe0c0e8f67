"""Magnetic compass: Earth field plus local sources (seeds/000 eq. 16–18), and the robot's own
disturbances (hard iron, soft iron, motor currents) with white noise.

Seed (seeds/000_b0d2d08e12d78625.txt, "Magnetic compass"): "The power of a magnetic field
vanishes inverse proportional to the squared distance"::

    F = 1 / d_MK^2 (in the direction L_M - L_K)          (16)
    F_tot = sum_i F_i                                     (17)–(18)
    "The influence of the north pole is just one of these force vectors, lets assume F_0."

Read: each source i contributes a horizontal vector of magnitude ``strength_i / d_i^2`` (strength
= field at 1 m, ``sim.world.MagneticSource``) pointing from the robot towards the source (the
extracted exponent ``2(L_M - L_K)`` is the unit direction vector fused into the power); the Earth
field is ``F_0``; the compass sees the vector sum (:func:`field_world`). Distances are floored at
``min_distance_m`` so a robot driving over a source does not read an infinite field.

Robot disturbances (beyond the seed; the standard magnetometer model of ArduPilot's compass
calibration / SITL ``SIM_MAG_*`` parameters)::

    B_m = S @ B_body + b_hard + M @ i + n,   n ~ N(0, noise_sigma_uT^2 I)

``S`` soft-iron matrix (3x3), ``b_hard`` hard-iron offset (uT, body FLU), ``M`` (3x2) field per
ampere of the left and right motor currents ``i``, the currents taken proportional to the wheel
speeds (``motor_current_A_per_mps``; a DC motor's current follows its load, and on a flat floor
the load grows with speed through friction; the sign flips with the direction of rotation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim.models._params import check_nonnegative, check_positive, params_from_dict
from sim.schema import ConfigError


def _identity() -> tuple[tuple[float, ...], ...]:
    return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class CompassErrorParams:
    """``[sensors.compass]`` error-model keys. Field in microtesla, body frame FLU."""

    ideal: bool = False
    hard_iron_uT: tuple[float, ...] = (0.0, 0.0, 0.0)
    soft_iron: tuple[tuple[float, ...], ...] = field(default_factory=_identity)
    motor_uT_per_A: tuple[tuple[float, ...], ...] = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
    motor_current_A_per_mps: float = 0.0
    noise_sigma_uT: float = 0.0
    min_distance_m: float = 0.05

    def __post_init__(self) -> None:
        if np.shape(self.hard_iron_uT) != (3,):
            raise ConfigError("'hard_iron_uT' must have 3 components")
        if np.shape(self.soft_iron) != (3, 3):
            raise ConfigError("'soft_iron' must be a 3x3 matrix (3 rows of 3)")
        if np.shape(self.motor_uT_per_A) != (3, 2):
            raise ConfigError("'motor_uT_per_A' must be 3 rows [left, right] (uT per A)")
        check_nonnegative(self.noise_sigma_uT, "noise_sigma_uT")
        check_positive(self.min_distance_m, "min_distance_m")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.compass") -> CompassErrorParams:
        return params_from_dict(cls, d, section)


def field_world(x: float, y: float, earth_uT: np.ndarray, sources: np.ndarray,
                min_distance_m: float = 0.05) -> np.ndarray:
    """Total field (uT, world frame x east / y north / z up) at ``(x, y)``: seeds/000 eq. 16–18.

    ``earth_uT`` (3,) is F_0; ``sources`` (k, 3) rows ``[x, y, strength_uT at 1 m]``.
    """
    total = np.array(earth_uT, dtype=float)
    if sources.shape[0]:
        v = sources[:, :2] - np.array([x, y])
        d = np.maximum(np.hypot(v[:, 0], v[:, 1]), min_distance_m)
        mag = sources[:, 2] / (d * d)
        total[:2] += (v / d[:, None] * mag[:, None]).sum(axis=0)
    return total


def world_to_body(field_w: np.ndarray, theta: float) -> np.ndarray:
    """Rotate a world-frame vector into the body frame FLU of a robot with heading ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c * field_w[0] + s * field_w[1], -s * field_w[0] + c * field_w[1],
                     field_w[2]])


def motor_currents_A(left_mps: float, right_mps: float, params: CompassErrorParams) -> np.ndarray:
    """Motor currents (A), proportional to wheel speed (see module doc)."""
    return params.motor_current_A_per_mps * np.array([left_mps, right_mps])


def measure(field_body_uT: np.ndarray, wheel_speeds_mps: tuple[float, float],
            params: CompassErrorParams, rng: np.random.Generator) -> np.ndarray:
    """Measured field (uT, body FLU) from the true one: ``S B + b_hard + M i + n``.
    Draws three normals per call (none when ideal)."""
    b = np.asarray(field_body_uT, dtype=float)
    if params.ideal:
        return b.copy()
    i = motor_currents_A(wheel_speeds_mps[0], wheel_speeds_mps[1], params)
    return (np.asarray(params.soft_iron) @ b + np.asarray(params.hard_iron_uT)
            + np.asarray(params.motor_uT_per_A) @ i
            + params.noise_sigma_uT * rng.standard_normal(3))


def heading_from_field(field_body_uT: np.ndarray, north_rad: float) -> float:
    """Robot heading (rad, world frame) a level compass implies, given magnetic north's direction
    ``north_rad`` (CCW from +x): the field points north, so its body bearing is north - theta."""
    bearing = math.atan2(field_body_uT[1], field_body_uT[0])
    th = north_rad - bearing
    return math.atan2(math.sin(th), math.cos(th))
