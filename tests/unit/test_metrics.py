"""bridge/estimation/metrics.py on synthetic series with known answers: alignment (linear
interpolation, unwrapped heading, no interpolation across a kidnap), RMSE, NEES of a consistent
and of an over-confident Gaussian estimator (fixed seed, bounds from the binomial and chi-square
laws), kidnap recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest
from koala_bridge.estimation.errors import EstimationError
from koala_bridge.estimation.metrics import (
    AlignedPoses,
    align,
    chi2_band,
    heading_rmse_deg,
    kidnap_recovery,
    nees,
    nees_summary,
    pose_rmse,
    tracking_metrics,
)
from scipy.stats import binom, chi2

SEED = 15
TAIL = 1e-4     # two-sided tail of every statistical bound below (a fixed seed: deterministic)


def motion(t: np.ndarray) -> np.ndarray:
    """A robot moving at constant velocity while its heading turns through +-pi."""
    return np.column_stack([0.5 + 0.2 * t, 1.0 - 0.1 * t,
                            np.angle(np.exp(1j * (math.pi - 0.3 + 0.4 * t)))])


def test_the_chi2_band_for_three_dof() -> None:
    lo, hi = chi2_band(3)
    assert lo == pytest.approx(0.2158, abs=1e-4)
    assert hi == pytest.approx(9.3484, abs=1e-4)


def test_align_interpolates_truth_at_the_estimate_times_through_the_wrap() -> None:
    truth_t = np.arange(0.0, 3.0 + 1e-9, 0.02)      # 50 Hz
    est_t = np.arange(0.01, 3.2, 0.05)              # 20 Hz, off the truth grid, runs past it
    a = align(truth_t, motion(truth_t), est_t, motion(est_t))
    assert a.t[0] == pytest.approx(0.01) and a.t[-1] <= 3.0   # beyond the truth: dropped
    # linear motion and a linear heading are interpolated exactly, also across +-pi
    assert np.max(np.abs(a.error)) < 1e-9
    assert pose_rmse(a) < 1e-9 and heading_rmse_deg(a) < 1e-7


def test_align_does_not_interpolate_across_a_kidnap() -> None:
    truth_t = np.arange(0.0, 2.0 + 1e-9, 0.02)
    truth = motion(truth_t)
    truth[truth_t > 1.0, 0] += 1.5                  # moved before the step after t = 1.0
    est_t = np.arange(0.0, 2.0 + 1e-9, 0.01)
    est = motion(est_t)
    est[est_t > 1.0, 0] += 1.5
    a = align(truth_t, truth, est_t, est, breaks=[1.0])
    assert 1.01 not in np.round(a.t, 6)             # between truth 1.00 and 1.02: dropped
    assert 1.0 in np.round(a.t, 6) and 1.02 in np.round(a.t, 6)
    assert np.max(np.abs(a.error)) < 1e-9
    # without the break the sample at 1.01 sees a truth half-way through the jump
    b = align(truth_t, truth, est_t, est)
    assert np.max(b.position_error) == pytest.approx(0.75, abs=1e-9)


def test_rmse_of_known_offsets_with_wrapped_headings() -> None:
    t = np.arange(10.0)
    truth = np.column_stack([t, t, np.full(10, -math.pi + 0.01)])
    est = truth + [0.03, 0.04, 0.0]
    est[:, 2] = math.pi - 0.01                      # 0.02 rad away across the wrap, not 2 pi
    a = AlignedPoses(t, truth, est)
    assert pose_rmse(a) == pytest.approx(0.05)
    assert heading_rmse_deg(a) == pytest.approx(math.degrees(0.02))


def test_nees_of_known_values() -> None:
    e = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.1]])
    p = np.array([np.diag([4.0, 1.0, 1.0]), np.diag([1.0, 1.0, 0.01])])
    assert nees(e, p) == pytest.approx([0.25, 5.0])
    singular = np.array([np.diag([1.0, 0.0, 1.0]), np.full((3, 3), np.nan)])
    assert np.all(np.isinf(nees(e, singular)))      # not a covariance: outside every band
    with pytest.raises(EstimationError, match="nees"):
        nees(e, p[:1])


def gaussian_run(n: int, rng: np.random.Generator, reported_scale: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Errors drawn from N(0, P_k) with random SPD P_k; the covariance reported is
    ``reported_scale * P_k``."""
    a = rng.normal(size=(n, 3, 3)) * [0.05, 0.05, 0.03]
    p = a @ np.swapaxes(a, 1, 2) + np.diag([1e-4, 1e-4, 1e-4])
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(p), rng.normal(size=(n, 3)))
    return e, reported_scale * p


def binomial_bounds(n: int, p: float) -> tuple[float, float]:
    return binom.ppf(TAIL / 2, n, p) / n, binom.ppf(1 - TAIL / 2, n, p) / n


def test_a_consistent_estimator_has_95_percent_in_band() -> None:
    n = 4000
    e, p = gaussian_run(n, np.random.default_rng(SEED), 1.0)
    s = nees_summary(nees(e, p))
    lo, hi = binomial_bounds(n, 0.95)
    assert lo <= s.fraction_in_band <= hi
    assert s.fraction_in_band >= 0.90                # the issue-15 target holds
    # the average NEES: N * mean ~ chi2(3 N) for independent samples
    m_lo, m_hi = chi2.ppf(TAIL / 2, 3 * n) / n, chi2.ppf(1 - TAIL / 2, 3 * n) / n
    assert m_lo <= s.mean <= m_hi
    assert s.mean_interval[0] < 3.0 < s.mean_interval[1]


def test_an_overconfident_estimator_fails_the_band() -> None:
    n = 4000
    e, p = gaussian_run(n, np.random.default_rng(SEED), 0.25)   # claims half the sigma
    s = nees_summary(nees(e, p))
    # eps = 4 chi2_3: inside the band when chi2_3 is in [lo / 4, hi / 4]
    lo, hi = chi2_band(3)
    expected = chi2.cdf(hi / 4, 3) - chi2.cdf(lo / 4, 3)
    b_lo, b_hi = binomial_bounds(n, expected)
    assert b_lo <= s.fraction_in_band <= b_hi
    assert s.fraction_in_band < 0.90
    assert s.fraction_above > 0.3
    assert s.mean > s.mean_interval[1]


def test_tracking_metrics_of_a_run() -> None:
    rng = np.random.default_rng(SEED)
    t = np.arange(0.0, 60.0, 0.05)
    e, p = gaussian_run(t.size, rng, 1.0)
    truth = motion(t)
    est = truth + e
    m = tracking_metrics(AlignedPoses(t, truth, est, p))
    assert m.n == t.size
    assert m.pose_rmse_m == pytest.approx(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
    assert m.nees is not None and m.nees.n == t.size


def test_kidnap_recovery_waits_for_the_error_to_stay_down() -> None:
    t = np.arange(0.0, 20.0, 0.05)
    d = np.full(t.size, 0.05)
    after = t > 5.0
    d[after] = np.clip(1.5 - 0.3 * (t[after] - 5.0), 0.05, None)   # below 0.2 m after 9.33 s
    d[(t >= 10.0) & (t < 10.2)] = 0.5                              # a relapse
    r = kidnap_recovery(t, d, 5.0, threshold_m=0.2, hold_s=1.0)
    assert r.t_recovered == pytest.approx(10.2)
    assert r.duration_s == pytest.approx(5.2)
    # a hold longer than the relapse-free stretch before it is not met by the first dip
    assert kidnap_recovery(t, d, 5.0, hold_s=0.5).t_recovered == pytest.approx(
        t[np.argmax(after & (d <= 0.2))])


def test_kidnap_recovery_never() -> None:
    t = np.arange(0.0, 20.0, 0.05)
    d = np.where(t > 5.0, 0.7, 0.05)
    assert kidnap_recovery(t, d, 5.0).t_recovered is None
    # below the threshold only in the last half second: the hold is not reached in the record
    d2 = np.where(t > 19.5, 0.1, d)
    r = kidnap_recovery(t, d2, 5.0)
    assert r.t_recovered is None and r.duration_s is None
    with pytest.raises(EstimationError, match="threshold_m"):
        kidnap_recovery(t, d, 5.0, threshold_m=0.0)
