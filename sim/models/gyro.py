"""Yaw-rate gyroscope error (seeds/000 eq. 15, extended with the Kalibr IMU noise model).

Seed (seeds/000_b0d2d08e12d78625.txt, "Gyroscope"): "a Gaussian error integrated over time"::

    theta_{n+1} = theta_n + (1 +- random() * sigma_Gyroscope) * dtheta_n      (15)

with ``dtheta_n`` "the relative rotation the koala did" in the step. Read: each sample's rotation
increment is scaled by ``1 + sigma_G * N(0, 1)``, i.e. a random per-sample *scale* error
(``scale_noise``), which integrates into a heading error whose variance grows with the rotation
made. As with the drive error, ``scale_noise`` is the per-sample sigma at ``reference_rate_hz``
and is rescaled at other sample rates (:func:`sim.noise.rate_scaled_sigma`) so the integrated
error of a given rotation does not depend on the rate.

Beyond the seed, the standard continuous-time IMU noise model of Kalibr (wiki "IMU Noise Model")
and of the allan-variance tools, so that measured densities can be entered directly::

    omega_m(t) = (1 + s + scale_noise * n_s) * omega(t) + b(t) + n(t)
    n(t): white, density sigma_g = gyroscope_noise_density        [rad/s/sqrt(Hz)]
    db/dt = sigma_bg * w(t),  sigma_bg = gyroscope_random_walk   [rad/s^2/sqrt(Hz)]

discretised for a sample interval ``dt`` as Kalibr specifies: white-noise sample sigma
``sigma_g / sqrt(dt)``; bias increment sigma ``sigma_bg * sqrt(dt)``. The integrated white noise
is the angle random walk: heading error variance ``sigma_g^2 * T`` after T seconds (grows as
sqrt(T)). ``b(0) = bias_rad_s + N(0, turn_on_bias_sigma^2)``: a fixed bias (what a calibration
measured, ``koala-bridge calibrate --write-config``) plus a turn-on bias drawn at reset; ``s`` a
fixed scale-factor error. With a finite ``bias_correlation_time_s`` the bias is a Gauss–Markov
process (Gazebo's IMU noise) with the same short-term walk density.

The simulator's stateful model is :class:`GyroErrorModel` (end of this module; the truth it
perturbs comes from ``sim/sensors/gyro.py``, its factory :func:`error_model` is registered in
``sim.models.ERROR_MODELS``). No compiled kernel: three scalars per step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Annotated, Any, ClassVar

import numpy as np
from koala_bridge.core.schema import Bool, Finite, FloatOrInf, NonNegative, Positive, section
from koala_bridge.sim.models._params import params_from_dict
from koala_bridge.sim.noise import BlockStream, Variates, gauss_markov_step, rate_scaled_sigma
from koala_bridge.sim.sensors.gyro import GyroTruth
from koala_bridge.sim.types import GyroReading
from pydantic import Field


@section
class GyroErrorParams:
    """``[sensors.gyro]`` error-model keys (SI units; Kalibr names for the two densities).

    Keyword defaults are the values of ``config/default.toml`` (sim/models/_params.py).
    """

    # Keys of the table that the sensor's section (sim/sensors/) owns and hands over.
    FROM_SENSOR: ClassVar[tuple[str, ...]] = ("ideal",)
    # The values of this model's error terms that mean "no such error" (not config defaults):
    # what `koala-bridge calibrate --write-config` writes for the terms it did not measure when
    # it switches the model on (bridge/calibration/config_update.py).
    ABSENT: ClassVar[Mapping[str, Any]] = MappingProxyType({
        "gyroscope_noise_density": 0.0, "gyroscope_random_walk": 0.0, "bias_rad_s": 0.0,
        "turn_on_bias_sigma": 0.0, "scale_factor_error": 0.0, "scale_noise": 0.0})

    ideal: Bool = False
    gyroscope_noise_density: NonNegative = 1.6968e-4  # rad/s/sqrt(Hz), white noise (ARW)
    gyroscope_random_walk: NonNegative = 1.9393e-5    # rad/s^2/sqrt(Hz), bias random walk
    # s; inf: pure random walk (Kalibr); finite: Gauss-Markov
    bias_correlation_time_s: Annotated[FloatOrInf, Field(gt=0)] = math.inf
    bias_rad_s: Finite = 0.0                 # rad/s, fixed bias (mean of b(0))
    turn_on_bias_sigma: NonNegative = 0.002  # rad/s, drawn once at reset
    scale_factor_error: Finite = 0.0         # fixed relative scale error s
    scale_noise: NonNegative = 0.01          # seeds/000 eq. 15 sigma_Gyroscope, per sample
    reference_rate_hz: Positive = 100.0      # sample rate at which scale_noise is per-sample

    @classmethod
    def from_dict(cls, d: dict[str, Any], section: str = "sensors.gyro") -> GyroErrorParams:
        return params_from_dict(cls, d, section)


@dataclass(frozen=True)
class GyroState:
    bias: float  # rad/s


def initial_state(params: GyroErrorParams, rng: np.random.Generator) -> GyroState:
    """Turn-on state: bias ~ N(bias_rad_s, turn_on_bias_sigma^2). Draws one variate (none when
    ideal)."""
    if params.ideal:
        return GyroState(0.0)
    return GyroState(float(params.bias_rad_s + params.turn_on_bias_sigma * rng.standard_normal()))


def measure(yaw_rate: float, dt: float, state: GyroState, params: GyroErrorParams,
            rng: Variates) -> tuple[float, GyroState]:
    """One gyro sample: ``(measured yaw rate rad/s, new state)``.

    ``yaw_rate`` is the true mean rate over the sample interval ``dt`` (s). Bias first propagates
    over ``dt`` (Kalibr order), then the sample is formed. Draws three normals per call.
    """
    if params.ideal:
        return yaw_rate, state
    z = np.asarray(rng.standard_normal(3))
    rate, bias = measure_with(yaw_rate, state.bias, params, step_constants(params, dt),
                              float(z[0]), float(z[1]), float(z[2]))
    return rate, GyroState(bias)


def step_constants(params: GyroErrorParams, dt: float) -> tuple[float, float, float, float]:
    """For a sample interval ``dt``: the bias decay ``phi`` (1 for the random walk), the sigma of
    the bias step, the per-sample scale sigma and the white-noise sample sigma (module doc)."""
    if math.isinf(params.bias_correlation_time_s):
        phi = 1.0
        bias_sigma = params.gyroscope_random_walk * math.sqrt(dt)
    else:
        tau = params.bias_correlation_time_s
        # Stationary sigma of the Gauss-Markov bias whose short-term walk density is sigma_bg.
        sigma_ss = params.gyroscope_random_walk * math.sqrt(tau / 2.0)
        phi = math.exp(-dt / tau)
        bias_sigma = sigma_ss * math.sqrt(1.0 - phi * phi)
    s_step = rate_scaled_sigma(params.scale_noise, 1.0 / dt, params.reference_rate_hz)
    return phi, bias_sigma, s_step, params.gyroscope_noise_density / math.sqrt(dt)


def measure_with(yaw_rate: float, bias: float, params: GyroErrorParams,
                 constants: tuple[float, float, float, float],
                 z_bias: float, z_scale: float, z_white: float) -> tuple[float, float]:
    """:func:`measure` with the constants of :func:`step_constants` and the three standard
    normals given (bias step, scale noise, white noise), the bias as a float:
    ``(measured yaw rate, new bias)``. The simulator's path."""
    phi, bias_sigma, s_step, white_sigma = constants
    bias = phi * bias + bias_sigma * z_bias
    rate = ((1.0 + params.scale_factor_error + s_step * z_scale) * yaw_rate + bias
            + white_sigma * z_white)
    return rate, bias


def measure_batch(yaw_rates: np.ndarray, dt: float, bias0: np.ndarray, params: GyroErrorParams,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised samples for ``R`` independent gyros over ``N`` steps (for tests, figures and
    the bench): ``yaw_rates`` (R, N), ``bias0`` (R,). Returns ``(rates (R, N), biases (R, N))``.
    Same model as :func:`measure` (not the same draw order)."""
    r, n = yaw_rates.shape
    if params.ideal:
        return yaw_rates.copy(), np.repeat(bias0[:, None], n, axis=1)
    if math.isinf(params.bias_correlation_time_s):
        steps = params.gyroscope_random_walk * math.sqrt(dt) * rng.standard_normal((r, n))
        bias = bias0[:, None] + np.cumsum(steps, axis=1)
    else:
        tau = params.bias_correlation_time_s
        sigma_ss = params.gyroscope_random_walk * math.sqrt(tau / 2.0)
        bias = np.empty((r, n))
        b = bias0.astype(float)
        for k in range(n):
            b = gauss_markov_step(b, sigma_ss, tau, dt, rng)
            bias[:, k] = b
    s_step = rate_scaled_sigma(params.scale_noise, 1.0 / dt, params.reference_rate_hz)
    scale = 1.0 + params.scale_factor_error + s_step * rng.standard_normal((r, n))
    white = params.gyroscope_noise_density / math.sqrt(dt) * rng.standard_normal((r, n))
    return scale * yaw_rates + bias + white, bias


# ------------------------------------------------------------------ the simulator's model


class GyroErrorModel:
    """The stateful gyro error model the simulator calls (``sim/sensors/gyro.py`` seam):
    the params, the per-run state, and ``measure(truth, variates)`` built on the functions
    above, drawing the same variates in the same order as :func:`measure`."""

    def __init__(self, params: GyroErrorParams, rate_hz: float,
                 rng: np.random.Generator) -> None:
        self.params = params
        self.period = 1.0 / rate_hz
        self.bias = initial_state(params, rng).bias    # turn-on bias
        self._dt = self.period
        self._constants = step_constants(params, self.period)

    def measure(self, truth: GyroTruth, rng: Variates) -> GyroReading:
        if self.params.ideal:
            return GyroReading(yaw_rate=truth.yaw_rate, truth_yaw_rate=truth.yaw_rate)
        dt = truth.interval_s if truth.interval_s > 0 else self.period
        if dt != self._dt:
            self._dt = dt
            self._constants = step_constants(self.params, dt)
        z = rng.normal_list(3) if isinstance(rng, BlockStream) else rng.standard_normal(3).tolist()
        rate, self.bias = measure_with(truth.yaw_rate, self.bias, self.params,
                                                  self._constants, z[0], z[1], z[2])
        return GyroReading(yaw_rate=rate, truth_yaw_rate=truth.yaw_rate)


def error_model(cfg: Any, rng: np.random.Generator) -> GyroErrorModel:
    """The simulator's factory (``sim.models.ERROR_MODELS``), called at every reset with the
    ``[sensors.gyro]`` config and the sensor's own generator."""
    return GyroErrorModel(cfg.errors, cfg.rate_hz, rng)
