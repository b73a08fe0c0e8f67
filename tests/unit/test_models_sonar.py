"""Sonar (seeds/004 US table, specular loss, late echoes, crosstalk, glitches).

Model: sim/models/sonar.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance, assert_rate, assert_uniform_counts
from koala_bridge.sim.models.sonar import (
    SonarErrorParams,
    distance_sigma,
    measure,
    reflect,
    same_cycle,
)
from koala_bridge.sim.noise import LookupTable

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"late_echo_probability": 0.0, "crosstalk_probability": 0.0,
         "glitch_probability": 0.0, "min_range_m": 0.0, "firing_groups": ()}


def make_params(**kw: object) -> SonarErrorParams:
    """SonarErrorParams with :data:`QUIET` under ``kw``."""
    return SonarErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

N = 20000
MAXR = 3.0


@pytest.mark.parametrize(("d", "sigma"), [(0.10, 0.001), (0.30, 0.007), (0.60, 0.025),
                                          (1.00, 0.066), (0.45, 0.016)])
def test_error_spread_at_the_seed004_table_ranges(d: float, sigma: float) -> None:
    rng = np.random.default_rng(int(d * 1000))
    r = measure(np.full((N, 1), d), np.zeros((N, 1)), MAXR, make_params(), rng)
    # power: IR's +-3% table instead of the ultrasonic +-6.6% one
    assert_normal_variance(r.ranges - d, sigma**2, mean=0.0, wrong=(sigma * 0.03 / 0.066) ** 2
                           if d >= 0.3 else (sigma * 1.5) ** 2)
    assert np.all(r.truth_ranges == d)


@pytest.mark.parametrize("d", [1.5, 2.0, 2.4])
def test_error_beyond_the_table_is_the_seeds_relative_6_6_percent(d: float) -> None:
    # seeds/004 "+-6.6 %": beyond the table's last row (1 m, +-6.6 cm) its relative error is held,
    # sigma = 0.066 d (13.2 cm at 2 m); the absolute hold read before (6.6 cm) must be rejected
    p = make_params()
    sigma = 0.066 * d
    assert float(distance_sigma(d, p.distance_error.x, p.distance_error.y)) == pytest.approx(sigma)
    # (a 5 m range here: no reading of the tails is cut off as 'no echo')
    r = measure(np.full((N, 1), d), np.zeros((N, 1)), 5.0, p, np.random.default_rng(int(d * 100)))
    assert_normal_variance(r.ranges - d, sigma**2, mean=0.0, wrong=0.066**2)
    # continuous at the last row, and the table itself inside it
    assert float(distance_sigma(1.0, p.distance_error.x, p.distance_error.y)) == 0.066
    assert float(distance_sigma(0.45, p.distance_error.x, p.distance_error.y)) == pytest.approx(
        0.016)


@pytest.mark.parametrize("wall_deg", [0.0, 8.0, 15.0, 20.0, 30.0, 60.0])
def test_the_seeds_two_vertical_rays_never_change_the_reading(wall_deg: float) -> None:
    # seeds/004: 3 horizontal rays + 2 rays "centered horizontally [that] go up and down
    # vertically". On a vertical wall at distance D and horizontal incidence t, a ray at elevation
    # e along the axis travels D / (cos t cos e) at incidence acos(cos t cos e): never nearer than
    # the centre ray, never a direct echo when the centre ray is lost. So the 3 horizontal rays
    # (config rays = 3) read exactly what the 5 would.
    half = math.radians(22.9) / 2
    t0 = math.radians(wall_deg)
    wall = 1.2                                            # perpendicular distance to the wall
    azim = np.array([-half, 0.0, half])
    inc_h = np.abs(t0 + azim)                             # wall normal at -t0 to the axis
    d_h = wall / np.cos(inc_h)
    cos_v = math.cos(t0) * math.cos(half)
    d_v = np.full(2, wall / cos_v)
    inc_v = np.full(2, math.acos(cos_v))
    exact = make_params(distance_error=LookupTable.from_rows([[0.0, 0.0], [1.0, 0.0]]),
                        late_echo_probability=0.0)
    three = measure(d_h[None, :], inc_h[None, :], MAXR, exact, np.random.default_rng(3))
    five = measure(np.concatenate([d_h, d_v])[None, :], np.concatenate([inc_h, inc_v])[None, :],
                   MAXR, exact, np.random.default_rng(3))
    assert np.array_equal(three.ranges, five.ranges, equal_nan=True)
    assert np.array_equal(three.truth_ranges, five.truth_ranges)


def test_default_firing_order_has_no_crosstalk_and_all_together_has() -> None:
    # Koala 2.5 manual 4.1: one sonar after the other, 20 ms each; the round trip to the 2.5 m
    # range takes 2 * 2.5 / 343 = 14.6 ms < 20 ms, so no echo of one ping reaches the next slot
    assert 2 * 2.5 / 343.0 < 0.020
    default = SonarErrorParams()
    assert not same_cycle(9, default.firing_groups).any()
    geo = _pair(1)
    d1 = math.hypot(0.5, 0.05)
    rays, inc = np.array([[np.inf], [d1]]), np.array([[np.nan], [0.0]])
    seq = make_params(crosstalk_probability=1.0, firing_groups=default.firing_groups)
    assert np.isnan(measure(rays, inc, MAXR, seq, np.random.default_rng(4), **geo).ranges[0])
    together = make_params(crosstalk_probability=1.0, firing_groups=())
    r = measure(rays, inc, MAXR, together, np.random.default_rng(4), **geo)
    assert r.kind[0] == 3 and np.isfinite(r.ranges[0])


def test_no_echo_beyond_the_critical_angle() -> None:
    p = make_params(critical_angle_deg=22.5)
    rays = np.full((N, 5), 1.0)
    inc = np.full((N, 5), math.radians(22.6))
    r = measure(rays, inc, MAXR, p, np.random.default_rng(50))
    assert np.all(np.isnan(r.ranges))
    assert np.all(r.truth_ranges == 1.0)                       # truth still sees the wall
    inc[:, 2] = math.radians(22.4)                             # one ray within: echo
    r = measure(rays, inc, MAXR, p, np.random.default_rng(50))
    assert not np.any(np.isnan(r.ranges))


def test_nearest_direct_ray_wins_and_truth_keeps_incidence() -> None:
    rays = np.array([[1.2, 0.9, 1.0, np.inf, 2.0]])
    inc = np.radians([[5.0, 40.0, 10.0, np.nan, 0.0]])
    exact = make_params(distance_error=LookupTable.from_rows([[0.0, 0.0], [1.0, 0.0]]))
    r = measure(rays, inc, MAXR, exact, np.random.default_rng(1))
    assert r.truth_ranges[0] == 0.9 and r.incidence[0] == pytest.approx(math.radians(40))
    assert r.ranges[0] == 1.0                                  # 0.9 lost (specular), 1.0 direct
    ideal = measure(rays, inc, MAXR, make_params(ideal=True), np.random.default_rng(1))
    assert ideal.ranges[0] == 0.9


def test_late_echo_rate_and_round_trip_length() -> None:
    p = make_params(late_echo_probability=0.3)
    rays = np.full((N, 1), 0.8)
    inc = np.full((N, 1), math.radians(60))
    leg = np.full((N, 1), 1.6)                                 # p1 -> p2 -> sensor
    r = measure(rays, inc, MAXR, p, np.random.default_rng(51), second_leg_m=leg)
    late = ~np.isnan(r.ranges)
    assert_rate(int(late.sum()), N, 0.3, wrong=0.33)
    # round trip (0.8 + 1.6) / 2 = 1.2 m, with the sigma at 1.2 m (6.6 % beyond the table)
    assert_mean(r.ranges[late], 1.2, 0.066 * 1.2)
    assert np.all(r.kind[late] == 2)


def _pair(n: int) -> dict[str, np.ndarray]:
    # Sonar 0 at the origin looking +x sees nothing; sonar 1 beside it hits a post at (0.5, 0.05),
    # inside sonar 0's cone: crosstalk path (0.5 + |p - s0|) / 2.
    return {
        "sensor_xy": np.array([[0.0, 0.0], [0.0, 0.1]]),
        "sensor_heading": np.array([0.0, 0.0]),
        "hit_xy": np.tile(np.array([[[np.nan, np.nan]], [[0.5, 0.05]]]), (1, 1, 1)),
    }


def test_crosstalk_rate_path_and_firing_groups() -> None:
    p = make_params(crosstalk_probability=0.2)
    geo = _pair(1)
    d1 = math.hypot(0.5, 0.05)
    rays = np.array([[np.inf], [d1]])
    inc = np.array([[np.nan], [0.0]])
    rng = np.random.default_rng(52)
    hits = []
    for _ in range(5000):
        r = measure(rays, inc, MAXR, p, rng, **geo)
        hits.append(r.ranges[0])
    hits_a = np.array(hits)
    heard = ~np.isnan(hits_a)
    assert_rate(int(heard.sum()), 5000, 0.2, wrong=0.25)
    expect = 0.5 * (d1 + math.hypot(0.5, 0.05))
    assert_mean(hits_a[heard], expect, 0.02, wrong=expect + 0.02)   # table sigma at 0.5 m
    separate = make_params(crosstalk_probability=1.0, firing_groups=((0,), (1,)))
    r = measure(rays, inc, MAXR, separate, rng, **geo)
    assert np.isnan(r.ranges[0])
    assert same_cycle(3, ((0, 2), (1,))).tolist() == [[False, False, True], [False, False, False],
                                                      [True, False, False]]


def test_glitch_rate_and_uniform_values() -> None:
    p = make_params(glitch_probability=0.05, min_range_m=0.2)
    r = measure(np.full((N, 1), 1.0), np.zeros((N, 1)), MAXR, p, np.random.default_rng(53))
    g = r.kind == 4
    assert_rate(int(g.sum()), N, 0.05, wrong=0.07)
    vals = r.ranges[g]
    assert vals.min() >= 0.2 and vals.max() <= MAXR
    assert_uniform_counts(np.histogram(vals, bins=10, range=(0.2, MAXR))[0])


def test_beyond_max_range_is_no_echo_and_reflect() -> None:
    r = measure(np.full((3, 2), 5.0), np.zeros((3, 2)), MAXR, make_params(),
                np.random.default_rng(1))
    assert np.all(np.isnan(r.ranges)) and np.all(np.isnan(r.truth_ranges))
    d = reflect(np.array([[1.0, 0.0]]), np.array([[-1.0, 0.0]]))
    assert d.tolist() == [[-1.0, 0.0]]


def test_same_seed_bit_identical() -> None:
    p = make_params(glitch_probability=0.1, late_echo_probability=0.5)
    args = (np.full((8, 5), 1.0), np.full((8, 5), 0.1), MAXR, p)
    a = measure(*args, np.random.default_rng(9)).ranges
    b = measure(*args, np.random.default_rng(9)).ranges
    assert np.array_equal(a, b, equal_nan=True)
