"""IR proximity (seeds/004 IR table, Webots ray weighting; sim/models/ir.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance
from koala_bridge.sim.models.ir import IrErrorParams, counts_from_distances, measure, ray_weights
from koala_bridge.sim.noise import LookupTable

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"count_noise_sigma": 0.0, "ambient_counts": 0.0, "ambient_noise_counts": 0.0,
         "ambient_saturation": 0.0}


def make_params(**kw: object) -> IrErrorParams:
    """IrErrorParams with :data:`QUIET` under ``kw``."""
    return IrErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

OFFSETS = np.array([-0.015, 0.0, 0.015])    # seeds/004: aperture 0.03 rad, 3 rays
# Linear response 10000 counts/m over [0, 1.1] m, so a distance error maps onto counts by a known
# slope and the rounding to integer counts (variance 1/12) is small against the spread.
SLOPE = 10000.0
# The placeholder Koala response of config/default.toml (range m, counts).
KOALA = LookupTable.from_rows(list(zip([0.00, 0.01, 0.02, 0.03, 0.05, 0.07, 0.10, 0.15, 0.20, 0.25],
                                       [1023, 1010, 920, 760, 470, 290, 150, 60, 20, 0],
                                       strict=True)))
LINEAR = LookupTable.from_rows([[0.0, 1.1 * SLOPE], [1.1, 0.0]])


def test_webots_gaussian_ray_weights() -> None:
    w = ray_weights(OFFSETS, 1.0)
    e = math.exp(-0.25)                     # t = a/2: exp(-(1/2)^2)
    assert w == pytest.approx(np.array([e, 1.0, e]) / (1 + 2 * e))
    assert ray_weights(np.array([0.0]), 1.0) == pytest.approx([1.0])


def test_response_table_and_reflectivity() -> None:
    d = np.array([[0.04, 0.04, 0.04], [np.inf, np.inf, np.inf]])
    w = ray_weights(OFFSETS, 1.0)
    c = counts_from_distances(d, w, 1.0, KOALA)
    assert c == pytest.approx([615.0, 0.0])          # halfway between 760 (3 cm) and 470 (5 cm)
    assert counts_from_distances(d, w, 0.5, KOALA) == pytest.approx(c / 2)


@pytest.mark.parametrize(("d", "sigma"), [(0.10, 0.0004), (0.30, 0.003), (0.60, 0.0125),
                                          (1.00, 0.03), (0.80, 0.02125)])
def test_distance_error_spread_follows_the_seed004_table(d: float, sigma: float) -> None:
    """Counts variance = (slope * sigma(d))^2 + 1/12 (rounding to integer counts)."""
    p = make_params(max_counts=20000)
    rng = np.random.default_rng(int(d * 100))
    n = 20000
    counts, _, truth = measure(np.full((n, 3), d), OFFSETS, LINEAR, p, rng)
    var = (SLOPE * sigma) ** 2 + 1.0 / 12.0
    # power: the same table read as half-widths of a uniform (Webots 6 reading) -> sigma^2/3
    assert_normal_variance(counts.astype(float), var, wrong=(SLOPE * sigma) ** 2 / 3 + 1 / 12)
    assert_mean(counts.astype(float), SLOPE * (1.1 - d), math.sqrt(var))


def test_ambient_light_reading_and_saturation() -> None:
    p = make_params(max_counts=40000, ambient_counts=4000.0,
                      ambient_noise_counts=10.0, ambient_saturation=0.5,
                      distance_error=LookupTable.from_rows([[0, 0], [1, 0]]))
    rng = np.random.default_rng(40)
    counts, amb, truth = measure(np.full((20000, 3), 0.1), OFFSETS, LINEAR, p, rng)
    assert np.all(truth == 10000)
    assert np.all(counts == 9500)            # 10000 * (1 - 0.5 * 4000 / 40000)
    assert_mean(amb.astype(float), 4000.0, 10.0)
    assert_normal_variance(amb.astype(float), 100.0 + 1 / 12, wrong=121.0)


def test_count_noise_and_ideal() -> None:
    p = make_params(max_counts=20000, count_noise_sigma=5.0,
                      distance_error=LookupTable.from_rows([[0, 0], [1, 0]]))
    counts, _, truth = measure(np.full((20000, 3), 0.5), OFFSETS, LINEAR, p,
                               np.random.default_rng(41))
    assert_normal_variance(counts - truth.astype(float), 25.0 + 1 / 12, mean=0.0, wrong=30.0)
    ideal = make_params(ideal=True, count_noise_sigma=50.0)
    c, _, t = measure(np.full((4, 3), 0.05), OFFSETS, KOALA, ideal, np.random.default_rng(1))
    assert np.array_equal(c, t)
    # out of range rays give the table's last value (0 counts), counts stay in [0, max]
    c, _, _ = measure(np.full((2, 3), np.inf), OFFSETS, KOALA, make_params(count_noise_sigma=3.0),
                      np.random.default_rng(2))
    assert np.all((c >= 0) & (c <= 1023))
