"""Camera landmark errors (seeds/000 eq. 5–14 as reconstructed; sim/models/camera.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import assert_mean, assert_normal_variance, assert_rate, assert_uniform_counts
from koala_bridge.sim.models.camera import (
    CameraErrorParams,
    distance_error_mean,
    distance_error_std,
    distance_term,
    far_sigma,
    measure,
    miss_probability,
    near_sigma,
    viewing_angle,
    wrong_id_probability,
)

# The error terms these tests do not study, off (config/default.toml switches them on; the
# params' keyword defaults are its values, tests/unit/test_config_schema.py).
QUIET = {"max_range_m": 3.0}


def make_params(**kw: object) -> CameraErrorParams:
    """CameraErrorParams with :data:`QUIET` under ``kw``."""
    return CameraErrorParams(**{**QUIET, **kw})  # type: ignore[arg-type]

P = make_params(p_perc=0.01, p_recog=0.02, min_range_m=0.1, max_range_m=3.0,
                      distance_base=2.0, dist=0.05, d_mid_m=1.0, far_doubling_m=1.0,
                      bearing_sigma_deg=2.0)
A120 = math.radians(120.0)
N = 20000


def _one_landmark(n: int, a_deg: float, d: float, a_max: float = A120, lid: int = 1,
                  bearing: float = 0.3) -> tuple[np.ndarray, ...]:
    return (np.full(n, lid), np.full(n, d), np.full(n, bearing), np.full(n, math.radians(a_deg)),
            np.full(n, a_max))


def test_seed_properties_of_the_miss_probability() -> None:
    # at 0 deg and near range (d_min) it is p_perc; it reaches 1 at d_max and at a_max/2
    assert miss_probability(0.0, P.min_range_m, A120, P) == pytest.approx(P.p_perc)
    assert miss_probability(0.0, P.max_range_m, A120, P) == pytest.approx(1.0)
    assert miss_probability(A120 / 2, 0.5, A120, P) == pytest.approx(1.0)
    assert miss_probability(0.0, 0.05, A120, P) == 1.0            # closer than d_min
    # the distance term is exponential at base 2: f(mid) = (sqrt(2) - 1) / (2 - 1)
    mid = 0.5 * (P.min_range_m + P.max_range_m)
    assert distance_term(mid, P) == pytest.approx(math.sqrt(2) - 1)
    # omnidirectional: a_max = 10000 deg leaves the miss rate flat in angle (< 0.0013 added)
    omni = math.radians(10000.0)
    assert miss_probability(math.pi, 0.1, omni, P) - P.p_perc < 0.0013


@pytest.mark.parametrize(
    ("a_deg", "d", "a_max_deg"),
    [(0.0, 0.1, 120.0), (20.0, 0.5, 120.0), (40.0, 1.5, 120.0), (0.0, 2.5, 120.0),
     (170.0, 1.0, 10000.0), (60.0, 0.8, 360.0)],
)
def test_empirical_miss_rate_matches_eq_5_6_8(a_deg: float, d: float, a_max_deg: float) -> None:
    a_max = math.radians(a_max_deg)
    rng = np.random.default_rng(int(a_deg * 10 + d * 100))
    m = measure(*_one_landmark(N, a_deg, d, a_max), all_ids=np.array([1]), params=P, rng=rng)
    p = float(miss_probability(math.radians(a_deg), d, a_max, P))
    missed = N - m.ids.size
    # power: a model that ignores the distance term (or the angle term) must be rejected
    wrong = float(np.minimum(1.0, 4 * math.radians(a_deg) ** 2 / a_max**2 + P.p_perc))
    if abs(wrong - p) < 0.01:
        wrong = min(1.0, p + 0.02) if p < 0.5 else p - 0.02
    assert_rate(missed, N, p, wrong=wrong)


def test_wrong_ids_are_uniform_over_the_other_landmarks_at_the_eq9_rate() -> None:
    rng = np.random.default_rng(5)
    all_ids = np.array([1, 2, 3, 4, 5])
    a_deg, d = 25.0, 1.2
    m = measure(*_one_landmark(N, a_deg, d, lid=3), all_ids=all_ids, params=P, rng=rng)
    seen = m.ids.size
    wrong = m.ids != 3
    pw = float(wrong_id_probability(math.radians(a_deg), d, A120, P))
    # eq. 9 literally (uniform over all n including the true id) would give pw * 4/5
    assert_rate(int(wrong.sum()), seen, pw, wrong=pw * 4 / 5)
    counts = np.array([(m.ids == i).sum() for i in (1, 2, 4, 5)])
    assert_uniform_counts(counts)


def test_single_landmark_cannot_be_misrecognised() -> None:
    m = measure(*_one_landmark(2000, 30.0, 1.0), all_ids=np.array([1]), params=P,
                rng=np.random.default_rng(6))
    assert np.all(m.ids == 1)


@pytest.mark.parametrize("d", [0.3, 1.0, 2.2])
def test_distance_error_mean_and_spread_match_eq_10_12(d: float) -> None:
    rng = np.random.default_rng(int(d * 10))
    params = make_params(p_perc=0.0, p_recog=0.0, min_range_m=0.0, max_range_m=100.0,
                               dist=0.05, d_mid_m=1.0, far_doubling_m=1.0)
    m = measure(*_one_landmark(N, 0.0, d), all_ids=np.array([1]), params=params, rng=rng)
    err = m.ranges - d
    mu, sd = float(distance_error_mean(d, params)), float(distance_error_std(d, params))
    # power: a zero-mean far term (the other reading of eq. 10) must be rejected at d >= d_mid
    assert_mean(err, mu, sd, wrong=0.0 if d >= 1.0 else None)
    # sample variance: asymptotically normal with variance (mu4 - sd^4)/n (mu4 from the sample)
    s2 = float(err.var(ddof=1))
    mu4 = float(np.mean((err - err.mean()) ** 4))
    half = 4.0 * math.sqrt((mu4 - s2**2) / N)
    assert abs(s2 - sd**2) <= half, (s2, sd**2, half)
    # the near term alone (eq. 12) would be dist*d; at d_mid both terms equal dist * d_mid
    assert float(near_sigma(1.0, params)) == pytest.approx(float(far_sigma(1.0, params)))


def test_bearing_error_is_gaussian_with_alpha_ang() -> None:
    params = make_params(p_perc=0.0, p_recog=0.0, min_range_m=0.0, max_range_m=100.0,
                               bearing_sigma_deg=2.0)
    m = measure(*_one_landmark(N, 0.0, 0.5, bearing=0.3), all_ids=np.array([1]), params=params,
                rng=np.random.default_rng(8))
    s = math.radians(2.0)
    assert_normal_variance(m.bearings - 0.3, s * s, mean=0.0, wrong=(1.1 * s) ** 2)


def test_ideal_reports_every_landmark_unchanged() -> None:
    params = make_params(ideal=True)
    args = _one_landmark(10, 80.0, 2.9)
    m = measure(*args, all_ids=np.array([1, 2]), params=params, rng=np.random.default_rng(1))
    assert m.ids.size == 10 and np.all(m.ranges == 2.9) and np.all(m.bearings == 0.3)


def test_viewing_angle() -> None:
    lm = np.array([[0.0, 0.0], [0.0, 0.0]])
    facing = np.array([0.0, math.pi / 2])
    a = viewing_angle(lm, facing, np.array([1.0, 0.0]))
    assert a == pytest.approx([0.0, math.pi / 2])
