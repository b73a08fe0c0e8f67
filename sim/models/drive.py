"""Drive-control error: what the floor does to each commanded wheel step (seeds/000 eq. 1–4).

Seed (seeds/000_b0d2d08e12d78625.txt, "Drive Control"), as extracted::

    L_{n+1} = L_n + [x_{n+1}, y_{n+1}]                  (1)
    theta_{n+1} = theta_n + arctan(y_{n+1} / x_{n+1})    (2)
    x_{n+1} = x_n * (1 +- random()) * Drive              (3)
    y_{n+1} = y_n * (1 +- random()) * Drive              (4)

"The simulator moves the koala ... discretely at a given frequency. So every time the location
changes the error applies ... The error is a Gaussian function."

Reading (docs/models.md §Drive): eq. 3–4 multiply the two components of each step's displacement
by independent factors ``(1 + Drive * N(0, 1))`` (the ``* Drive`` outside the bracket is the
garbled position of the error rate: with it outside, a zero-error robot would not move), and
eq. 2 lets the heading follow from the perturbed components. Taken in world axes (x east,
y north) the error would depend on the compass direction of travel (none along the axes, most at
45°), which no floor does; taken in the robot frame a straight step has ``y = 0`` and would never
be perturbed. The frame-free reading that keeps "two independent multiplicative Gaussian errors
per step, the heading change resulting from them" is per *wheel*: each wheel's step displacement
is multiplied by ``1 + sigma * N(0, 1)``, and the heading change follows from their difference
(differential-drive kinematics, the role of eq. 2). It perturbs straight runs, arcs and turns on
the spot alike, and is isotropic.

Step rate: the seed applies ``Drive`` per simulator step. ``drive_error`` is that per-step
sigma *at* ``reference_rate_hz``; at another step rate the per-step sigma is rescaled by
:func:`sim.noise.rate_scaled_sigma` so that the error accumulated over a given distance is the same
(variance ``drive_error^2 * d_step_ref * D`` for a distance D covered in steps of length
``d_step_ref = v / reference_rate_hz``). With the default config (100 Hz step, reference 100 Hz)
the model is the seed's, as written.

Wall slip (beyond the seed): while the robot is in contact with a wall its wheels slip; each
wheel realises an independent fraction ``U(wall_traction_min, wall_traction_max)`` of its step, so
pushing against a wall twists the robot. The encoders still count the *commanded* rotation
(the caller reports odometry from the commanded steps), so dead reckoning drifts from the truth
pose as on the real robot.

The simulator's stateful model is :class:`DriveErrorModel` (end of this module; the motion it
perturbs comes from ``sim/robot.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). No compiled kernel: two wheels per step are cheapest in plain Python.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.schema import Bool, ConfigError, NonNegative, Positive, Probability, section
from koala_bridge.sim.models._params import params_from_dict
from koala_bridge.sim.noise import BlockStream, Variates, rate_scaled_sigma
from koala_bridge.sim.robot import Motion, RobotState, arc_displacement


@section
class DriveErrorParams:
    """``[robot.drive_error]``. Units: fractions (relative sigma), Hz.

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that [robot.drive_error] owns and hands over (sim/robot.py DriveConfig).
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal",)
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({"drive_error": 0.0})

    ideal: Bool = False
    drive_error: NonNegative = 0.1       # seeds/000 eq. 3–4 "Drive": relative sigma per wheel step
    reference_rate_hz: Positive = 100.0  # step rate at which drive_error is the per-step sigma
    wall_traction_min: Probability = 0.3  # fraction of each wheel's step realised in wall contact
    wall_traction_max: Probability = 0.9

    def __post_init__(self) -> None:
        if not 0.0 <= self.wall_traction_min <= self.wall_traction_max <= 1.0:
            raise ConfigError("need 0 <= wall_traction_min <= wall_traction_max <= 1")

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "robot.drive_error") -> DriveErrorParams:
        return params_from_dict(cls, d, section)


def perturb_wheel_steps(
    left_m: float,
    right_m: float,
    step_hz: float,
    params: DriveErrorParams,
    rng: Variates,
    in_contact: bool = False,
) -> tuple[float, float]:
    """Realised wheel displacements (m) for commanded ones, one simulator step.

    ``left_m``/``right_m``: commanded wheel surface displacements this step (m, forward > 0).
    ``step_hz``: the simulator step rate (1/dt). Returns the displacements the floor lets the
    wheels make; the caller integrates them into the truth pose with its kinematics. Draws exactly
    four variates per call (two normals, two uniforms) whatever the flags, so the stream does not
    depend on contact history. ``ideal`` returns the commanded steps and draws nothing.
    """
    if params.ideal:
        return left_m, right_m
    eps = np.asarray(rng.standard_normal(2))
    u = np.asarray(rng.random(2))
    sigma = rate_scaled_sigma(params.drive_error, step_hz, params.reference_rate_hz)
    return perturb_wheel_steps_with(left_m, right_m, sigma, params, float(eps[0]), float(eps[1]),
                                    float(u[0]), float(u[1]), in_contact)


def perturb_wheel_steps_with(
    left_m: float, right_m: float, sigma: float, params: DriveErrorParams,
    eps_left: float, eps_right: float, u_left: float, u_right: float, in_contact: bool,
) -> tuple[float, float]:
    """:func:`perturb_wheel_steps` with the variates given (two standard normals, two uniforms)
    and the per-step ``sigma`` already rate-scaled: the simulator's path."""
    left = left_m * (1.0 + sigma * eps_left)
    right = right_m * (1.0 + sigma * eps_right)
    if in_contact:
        lo, hi = params.wall_traction_min, params.wall_traction_max
        left *= lo + (hi - lo) * u_left
        right *= lo + (hi - lo) * u_right
    return left, right


def integrate_wheel_steps(
    x: float, y: float, theta: float, left_m: float, right_m: float, wheel_base_m: float
) -> tuple[float, float, float]:
    """Exact differential-drive arc for one step: eq. 1 (L += displacement) and eq. 2 (heading
    changes by the rotation the two wheel steps imply). Returns ``(x, y, theta)`` with theta
    wrapped to (-pi, pi]."""
    ds = 0.5 * (left_m + right_m)
    dth = (right_m - left_m) / wheel_base_m
    if abs(dth) < 1e-12:
        dx, dy = ds * math.cos(theta), ds * math.sin(theta)
    else:
        r = ds / dth
        dx = r * (math.sin(theta + dth) - math.sin(theta))
        dy = -r * (math.cos(theta + dth) - math.cos(theta))
    th = wrap_angle(theta + dth)
    return x + dx, y + dy, th


def heading_error_variance(
    steps_left_m: np.ndarray, steps_right_m: np.ndarray, wheel_base_m: float, sigma_step: float
) -> float:
    """Variance of the accumulated heading error (rad^2) of a run of steps, no wall contact:
    ``sigma^2 * sum(l_k^2 + r_k^2) / b^2`` (independent per-wheel factors, dtheta = (r - l)/b)."""
    return float(sigma_step**2 * np.sum(steps_left_m**2 + steps_right_m**2) / wheel_base_m**2)


# ------------------------------------------------------------------ the simulator's model


class DriveErrorModel:
    """seeds/000 eq. 1–4 per wheel plus wall slip; implements ``sim.robot.DriveErrorSeam``.

    The truth pose moves by the perturbed wheel steps; the motion's wheel travel (what the
    encoders count) stays the commanded one.
    """

    def __init__(self, params: DriveErrorParams, wheel_base_m: float, dt: float
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
        left, right = perturb_wheel_steps_with(
            ideal.left_m, ideal.right_m, self.sigma, self.params, eps[0], eps[1], u[0], u[1],
            state.collided)
        dt = self.dt
        dx, dy, dth = arc_displacement(left / dt, right / dt, self.wheel_base_m, dt)
        return Motion(dx, dy, dth, ideal.left_m, ideal.right_m)


def error_model(cfg: Any, rng: np.random.Generator) -> DriveErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``): the whole SimConfig, since the
    model needs the wheel base and the step."""
    # The drive model needs the wheel base and the step: its factory gets the whole SimConfig.
    return DriveErrorModel(cfg.robot.drive.errors, cfg.robot.wheel_base_m, cfg.sim.dt_s)
