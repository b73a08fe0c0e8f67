"""sim/noise.py: the shared primitives against their own definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_normal_variance

from sim.noise import LookupTable, gauss_markov_step, random_walk_step, rate_scaled_sigma
from sim.schema import ConfigError


def test_random_walk_variance_grows_linearly_whatever_dt() -> None:
    rng = np.random.default_rng(10)
    q = 0.3
    for dt, steps in ((0.01, 400), (0.04, 100)):   # both T = 4 s
        x = np.zeros(4000)
        for _ in range(steps):
            x = random_walk_step(x, q, dt, rng)
        assert_normal_variance(x, q * q * 4.0, mean=0.0, wrong=q * q * 4.0 * 1.25)


def test_gauss_markov_stationary_variance_and_correlation() -> None:
    rng = np.random.default_rng(11)
    sigma, tau, dt = 2.0, 0.5, 0.1
    x0 = sigma * rng.standard_normal(20000)        # start in the stationary distribution
    x1 = gauss_markov_step(x0, sigma, tau, dt, rng)
    assert_normal_variance(x1, sigma**2, mean=0.0, wrong=sigma**2 * 1.1)
    # lag-1 correlation exp(-dt/tau): residual x1 - phi x0 has variance sigma^2 (1 - phi^2)
    phi = math.exp(-dt / tau)
    assert_normal_variance(x1 - phi * x0, sigma**2 * (1 - phi**2), mean=0.0,
                           wrong=sigma**2 * (1 - (phi - 0.05) ** 2))
    with pytest.raises(ValueError):
        gauss_markov_step(x0, sigma, math.inf, dt, rng)


def test_rate_scaled_sigma_keeps_accumulated_variance() -> None:
    # N steps of D/N with relative sigma: variance sigma^2 D^2 / N must not depend on N.
    s100 = rate_scaled_sigma(0.1, 100.0, 100.0)
    s400 = rate_scaled_sigma(0.1, 400.0, 100.0)
    assert s100 == pytest.approx(0.1)
    assert s100**2 / 100 == pytest.approx(s400**2 / 400)


def test_lookup_table_interpolates_and_holds_ends() -> None:
    t = LookupTable.from_rows([[0.0, 10.0, 0.0], [1.0, 20.0, 2.0]])
    assert t.value(0.25) == pytest.approx(12.5)
    assert t.noise(0.5) == pytest.approx(1.0)
    assert t.value(5.0) == pytest.approx(20.0)
    assert t.value(-1.0) == pytest.approx(10.0)
    with pytest.raises(ConfigError):
        LookupTable.from_rows([[0.0, 1.0], [0.0, 2.0]])
    with pytest.raises(ConfigError):
        LookupTable.from_rows([[0.0, 1.0]])
