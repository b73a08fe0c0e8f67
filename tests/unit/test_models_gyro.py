"""Gyroscope (seeds/000 eq. 15 + Kalibr IMU noise model; sim/models/gyro.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_normal_variance
from koala_bridge.sim.models.gyro import (
    GyroErrorParams,
    GyroState,
    initial_state,
    measure,
    measure_batch,
)

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"gyroscope_noise_density": 0.0, "gyroscope_random_walk": 0.0,
         "turn_on_bias_sigma": 0.0, "scale_noise": 0.0}


def make_params(**kw: object) -> GyroErrorParams:
    """GyroErrorParams with :data:`QUIET` under ``kw``."""
    return GyroErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

DT = 0.01   # 100 Hz
R = 2000    # independent gyros


def test_angle_random_walk_grows_as_sqrt_t() -> None:
    """Integrated white noise of density sigma_g: heading error variance sigma_g^2 T."""
    sg = 0.01
    p = make_params(gyroscope_noise_density=sg)
    rng = np.random.default_rng(20)
    n = 1600
    rates, _ = measure_batch(np.zeros((R, n)), DT, np.zeros(R), p, rng)
    heading = np.cumsum(rates, axis=1) * DT
    for t in (1.0, 4.0, 16.0):
        k = int(round(t / DT)) - 1
        # power: a discretisation without 1/sqrt(dt) (sigma_g per sample) would give
        # sigma_g^2 dt T, and a linear growth would give sigma_g^2 T^2.
        assert_normal_variance(heading[:, k], sg * sg * t, mean=0.0, wrong=sg * sg * t * 1.5)
    ratio = heading[:, -1].std() / heading[:, 399].std()
    assert 1.7 < ratio < 2.3     # sqrt(16/4) = 2


def test_scalar_measure_white_noise_sample_sigma() -> None:
    sg = 0.01
    p = make_params(gyroscope_noise_density=sg)
    rng = np.random.default_rng(21)
    st = GyroState(0.0)
    x = np.empty(20000)
    for i in range(x.size):
        x[i], st = measure(0.0, DT, st, p, rng)
    assert_normal_variance(x, sg * sg / DT, mean=0.0, wrong=sg * sg / DT * 1.1)


def test_bias_random_walk_variance_is_sigma_bg_squared_t() -> None:
    sbg = 0.002
    p = make_params(gyroscope_random_walk=sbg)
    rng = np.random.default_rng(22)
    _, bias = measure_batch(np.zeros((R, 1000)), DT, np.zeros(R), p, rng)
    assert_normal_variance(bias[:, -1], sbg * sbg * 10.0, mean=0.0, wrong=sbg * sbg * 15.0)
    # and the scalar path propagates the same walk
    st = GyroState(0.0)
    ends = np.empty(3000)
    for r in range(ends.size):
        st = GyroState(0.0)
        for _ in range(10):
            _, st = measure(0.0, DT, st, p, rng)
        ends[r] = st.bias
    assert_normal_variance(ends, sbg * sbg * 0.1, mean=0.0, wrong=sbg * sbg * 0.1 * 1.5)


def test_gauss_markov_bias_is_stationary_with_sigma_bg_sqrt_tau_over_2() -> None:
    sbg, tau = 0.002, 2.0
    p = make_params(gyroscope_random_walk=sbg, bias_correlation_time_s=tau)
    rng = np.random.default_rng(23)
    s_ss = sbg * math.sqrt(tau / 2)
    b0 = s_ss * rng.standard_normal(R)
    _, bias = measure_batch(np.zeros((R, 300)), DT, b0, p, rng)
    assert_normal_variance(bias[:, -1], s_ss**2, mean=0.0, wrong=s_ss**2 * 1.5)


def test_turn_on_bias() -> None:
    p = make_params(turn_on_bias_sigma=0.005)
    rng = np.random.default_rng(24)
    b = np.array([initial_state(p, rng).bias for _ in range(5000)])
    assert_normal_variance(b, 0.005**2, mean=0.0, wrong=0.0055**2)


@pytest.mark.parametrize("rate_hz", [100.0, 400.0])
def test_eq15_scale_noise_integrates_rate_invariantly(rate_hz: float) -> None:
    """Turning at 1 rad/s for 2 s: heading error variance s^2 omega^2 T / f_ref at any rate."""
    s, w, t = 0.05, 1.0, 2.0
    p = make_params(scale_noise=s, reference_rate_hz=100.0)
    rng = np.random.default_rng(int(rate_hz))
    dt = 1.0 / rate_hz
    n = int(round(t * rate_hz))
    rates, _ = measure_batch(np.full((R, n), w), dt, np.zeros(R), p, rng)
    err = rates.sum(axis=1) * dt - w * t
    var = s * s * w * w * t / 100.0
    assert_normal_variance(err, var, mean=0.0, wrong=var * 100.0 / rate_hz if rate_hz != 100
                           else var * 1.5)


def test_fixed_scale_factor_and_ideal() -> None:
    p = make_params(scale_factor_error=0.02)
    r, st = measure(1.0, DT, GyroState(0.0), p, np.random.default_rng(1))
    assert r == pytest.approx(1.02)
    ideal = make_params(ideal=True, gyroscope_noise_density=1.0)
    rng = np.random.default_rng(1)
    assert measure(0.7, DT, GyroState(0.0), ideal, rng)[0] == 0.7
    assert initial_state(ideal, rng).bias == 0.0


def test_from_dict_kalibr_names() -> None:
    p = GyroErrorParams.from_dict({"gyroscope_noise_density": 1.6968e-4,
                                   "gyroscope_random_walk": 1.9393e-5})
    assert p.gyroscope_noise_density == 1.6968e-4
