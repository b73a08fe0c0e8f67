"""Camera landmark errors (seeds/000 eq. 5–14, eq. 5–8 multiplicative; sim/models/camera.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _stats import (
    assert_mean,
    assert_normal_variance,
    assert_rate,
    assert_uniform_counts,
    binomial_interval,
)
from koala_bridge.sim.models.camera import (
    CameraErrorParams,
    distance_error_mean,
    distance_error_std,
    distance_factor,
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
                      distance_base=2.0, dist=0.05, d_mid_m=1.0, far_doubling_m=2.0,
                      bearing_sigma_deg=2.0)
A120 = math.radians(120.0)
N = 20000


def _one_landmark(n: int, a_deg: float, d: float, a_max: float = A120, lid: int = 1,
                  bearing: float = 0.3) -> tuple[np.ndarray, ...]:
    return (np.full(n, lid), np.full(n, d), np.full(n, bearing), np.full(n, math.radians(a_deg)),
            np.full(n, a_max))


def test_seed_properties_of_the_miss_probability() -> None:
    # eq. 6: g(d) = 2^((d - d_max)/d_max) "reaches its maximum (1) at the maximum sight distance"
    # and scales p_perc: P_miss = p_perc at 0 deg and d_max, p_perc / 2 next to the camera
    assert miss_probability(0.0, P.max_range_m, A120, P) == pytest.approx(P.p_perc)
    assert float(distance_factor(0.0, P)) == pytest.approx(0.5)
    assert float(distance_factor(P.max_range_m / 2, P)) == pytest.approx(2 ** -0.5)
    assert miss_probability(0.0, P.min_range_m, A120, P) == pytest.approx(
        P.p_perc * 2 ** ((P.min_range_m - P.max_range_m) / P.max_range_m))
    assert miss_probability(A120 / 2, 0.5, A120, P) == pytest.approx(1.0)   # angle term alone
    assert miss_probability(0.0, 0.05, A120, P) == 1.0            # closer than d_min
    assert miss_probability(0.0, P.max_range_m + 0.01, A120, P) == 1.0  # beyond d_max
    # omnidirectional: a_max = 10000 deg leaves the miss rate flat in angle (< 0.0013 added)
    omni = math.radians(10000.0)
    assert miss_probability(math.pi, 0.1, omni, P) - miss_probability(0.0, 0.1, omni, P) < 0.0013


# The default camera (config/default.toml: d_min 0.1 m, d_max 4 m, p_perc = p_recog = 0.01) head-on
# at 1 m and 2 m: P = 0.01 * 2^((d - 4)/4) = 0.595 % and 0.707 % (seeds/000 eq. 5–8 multiplied).
# The additive reading used before (4a^2/a_max^2 + p_perc + (2^((d - d_min)/(d_max - d_min)) - 1))
# gave 18.3 % and 41.1 %; a distance term dropped (p_perc flat) gives 1 %.
ADDITIVE = {1.0: 0.01 + 2 ** (0.9 / 3.9) - 1, 2.0: 0.01 + 2 ** (1.9 / 3.9) - 1}
N_DEFAULT = 100000


@pytest.mark.parametrize("d", [1.0, 2.0])
def test_default_camera_miss_and_wrong_id_rates_at_1_and_2_m(d: float) -> None:
    params = CameraErrorParams()                 # the keyword defaults are config/default.toml's
    p = 0.01 * 2 ** ((d - 4.0) / 4.0)
    assert float(miss_probability(0.0, d, A120, params)) == pytest.approx(p)
    assert float(wrong_id_probability(0.0, d, A120, params)) == pytest.approx(p)
    all_ids = np.array([1, 2, 3, 4, 5])
    m = measure(*_one_landmark(N_DEFAULT, 0.0, d, lid=2), all_ids=all_ids, params=params,
                rng=np.random.default_rng(int(d * 1000)))
    missed = N_DEFAULT - m.ids.size
    # Binomial(N, p) at alpha = 1e-4, and a flat p_perc (no distance factor) must be rejected ...
    assert_rate(missed, N_DEFAULT, p, wrong=0.01)
    # ... and so, by far, must the additive reading (18 % / 41 %)
    lo_add = binomial_interval(N_DEFAULT, ADDITIVE[d])[0]
    assert missed < lo_add
    # wrong ids among the perceived: Binomial(seen, p), the same distribution (eq. 9)
    seen = m.ids.size
    assert_rate(int((m.ids != 2).sum()), seen, p, wrong=0.01)


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
    # power: the additive reading (distance term at full weight) must be rejected; where it and
    # the model meet (the angle term saturates), a rate 0.02 off
    u = (d - P.min_range_m) / (P.max_range_m - P.min_range_m)
    wrong = float(min(1.0, 4 * math.radians(a_deg) ** 2 / a_max**2 + P.p_perc + 2**u - 1))
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
                               dist=0.05, d_mid_m=1.0, far_doubling_m=2.0)
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


def test_far_error_doubles_every_2_m_as_eq_11_reads() -> None:
    # eq. 11 as extracted: eps_far = dist d_mid 2^((d - d_mid)/2); the default far_doubling_m is 2
    params = CameraErrorParams(p_perc=0.0, p_recog=0.0)
    assert params.far_doubling_m == 2.0
    assert float(far_sigma(3.0, params)) == pytest.approx(2 * float(far_sigma(1.0, params)))
    # at 3.9 m the 1 m doubling read before gave 2^(2.9/2) = 2.7 times the text's far error
    old = CameraErrorParams(p_perc=0.0, p_recog=0.0, far_doubling_m=1.0)
    assert float(far_sigma(3.9, old) / far_sigma(3.9, params)) == pytest.approx(2 ** 1.45)
    # empirical mean at 3 m: eps_far sqrt(2/pi) = 0.080 m, the 1 m doubling's 0.160 m rejected
    d = 3.0
    m = measure(*_one_landmark(N, 0.0, d), all_ids=np.array([1]), params=params,
                rng=np.random.default_rng(31))
    assert m.ids.size == N
    assert_mean(m.ranges - d, float(distance_error_mean(d, params)),
                float(distance_error_std(d, params)),
                wrong=float(distance_error_mean(d, old)))


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
