"""sim/noise.py: the shared primitives against their own definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_normal_variance
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim.noise import (
    BlockStream,
    LookupTable,
    gauss_markov_step,
    random_walk_step,
    rate_scaled_sigma,
)


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


def test_block_stream_is_the_same_sequence_whatever_the_blocks_and_the_mix() -> None:
    small = BlockStream(np.random.default_rng(7), block=5)
    big = BlockStream(np.random.default_rng(7), block=4096)
    # small draws normals and uniforms interleaved, in odd sizes, as arrays and as floats
    got_n: list[float] = []
    got_u: list[float] = []
    for i in range(60):
        got_n += small.normals(i % 4 + 1).tolist() if i % 2 else small.normal_list(i % 3 + 1)
        got_u += small.uniforms(i % 5 + 1).tolist() if i % 3 else small.uniform_list(2)
    assert got_n == big.normals(len(got_n)).tolist()
    assert got_u == big.uniforms(len(got_u)).tolist()
    # the Generator-like methods read the same streams
    a = BlockStream(np.random.default_rng(7))
    assert np.array_equal(a.standard_normal((2, 3)).ravel(), np.array(got_n[:6]))
    assert float(a.random()) == got_u[0]
    # normals and uniforms are two independent child streams of the sensor's generator
    assert set(got_n).isdisjoint(got_u)
