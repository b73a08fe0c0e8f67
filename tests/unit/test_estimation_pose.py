"""Pose tracking EKF: model pieces, Jacobians and Monte-Carlo consistency on a synthetic run."""

from __future__ import annotations

import math

import numpy as np
import pytest
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.estimation import PoseTracker, PoseTrackerParams, heading_from_field
from koala_bridge.estimation.pose_filter import (
    HEADING_H,
    landmark_model,
    odometry_increment,
    predict,
    update,
)
from scipy.stats import chi2

LANDMARKS = np.array([[0.05, 1.95], [1.95, 1.95], [1.95, 0.05], [0.05, 0.05]])


def test_odometry_increment_and_noise_free_prediction_follow_the_arc() -> None:
    ds, dth = odometry_increment(0.1, 0.1 + 0.285 * 0.2, 0.285)
    assert ds == pytest.approx(0.1285) and dth == pytest.approx(0.2)
    # A full circle of radius 0.5 m in 1000 small steps comes back to the start.
    x, P = np.array([1.0, 1.0, 0.0, 0.0]), np.zeros((4, 4))
    n = 1000
    for _ in range(n):
        x, P = predict(x, P, 2 * math.pi * 0.5 / n, 2 * math.pi / n, np.zeros((2, 2)))
    np.testing.assert_allclose(x[:2], [1.0, 1.0], atol=1e-9)
    assert abs(wrap_angle(x[2])) < 1e-9
    np.testing.assert_array_equal(P, 0.0)


def test_gyro_bias_is_subtracted_over_the_integration_time() -> None:
    x = np.array([0.0, 0.0, 0.0, 0.05])
    x, _ = predict(x, np.eye(4) * 1e-4, 0.0, 0.5, np.zeros((2, 2)), bias_time=2.0)
    assert x[2] == pytest.approx(0.4)


def test_landmark_jacobian_matches_finite_differences() -> None:
    x = np.array([0.7, 0.4, 0.9, 0.01])
    hx, H = landmark_model(x, [1.9, 1.7])
    eps = 1e-7
    for j in range(4):
        dx = np.zeros(4)
        dx[j] = eps
        hp, _ = landmark_model(x + dx, [1.9, 1.7])
        num = (hp - hx) / eps
        num[1] = wrap_angle(num[1] * eps) / eps
        np.testing.assert_allclose(H[:, j], num, atol=1e-5)


def test_scalar_heading_update_is_the_textbook_fusion() -> None:
    x = np.array([0.0, 0.0, 3.1, 0.0])
    P = np.diag([1.0, 1.0, 0.04, 1e-4])
    xn, Pn = update(x, P, [-3.1], [[0.01]], HEADING_H, [x[2]], (0,))
    # the innovation wraps: -3.1 - 3.1 = 0.083 rad, not -6.2
    innov = wrap_angle(-3.1 - 3.1)
    assert wrap_angle(xn[2] - (3.1 + 0.04 / 0.05 * innov)) == pytest.approx(0.0, abs=1e-12)
    assert Pn[2, 2] == pytest.approx(1 / (1 / 0.04 + 1 / 0.01))


def test_heading_from_field_round_trip() -> None:
    north = math.radians(90.0)
    for theta in np.linspace(-3.1, 3.1, 13):
        a = north - theta  # field direction seen from the body
        m = [20 * math.cos(a) + 3.0, 20 * math.sin(a) - 1.0, -43.0]
        assert wrap_angle(heading_from_field(m, north, [3.0, -1.0, 0.0]) - theta) == pytest.approx(
            0.0, abs=1e-12
        )


# --------------------------------------------------------------------------- Monte Carlo

DT = 0.01
ODO_VAR_PER_M = 1e-4  # m^2/m
GYRO_DENSITY = 2e-3  # rad/s/sqrt(Hz)
GYRO_RW = 1e-4  # rad/s^2/sqrt(Hz)
COMPASS_SIGMA = math.radians(3.0)
RANGE_SIGMA = 0.03
BEARING_SIGMA = math.radians(2.0)


def synthetic_run(
    seed: int, steps: int, landmarks: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth and EKF estimates on a figure-of-eight-ish path in a 2 m box, with every sensor's
    noise drawn from the filter's own model. Returns (truth (steps, 4), est (steps, 4),
    covariances (steps, 4, 4))."""
    rng = np.random.default_rng(seed)
    P0 = np.diag([0.02**2, 0.02**2, math.radians(3) ** 2, 0.01**2])
    truth = np.array([1.0, 1.0, 0.3, 0.02])
    x = truth + rng.multivariate_normal(np.zeros(4), P0)
    P = P0.copy()
    T, E, C = [], [], []
    for k in range(steps):
        t = k * DT
        v = 0.15 + 0.05 * math.sin(0.7 * t)
        w = 0.6 * math.sin(0.25 * t)
        ds, dth = v * DT, w * DT
        thm = truth[2] + 0.5 * dth
        truth = np.array(
            [truth[0] + ds * math.cos(thm), truth[1] + ds * math.sin(thm),
             wrap_angle(truth[2] + dth),
             truth[3] + rng.normal(0, GYRO_RW * math.sqrt(DT))]
        )
        ds_m = ds + rng.normal(0, math.sqrt(ODO_VAR_PER_M * ds))
        gyro = w + truth[3] + rng.normal(0, GYRO_DENSITY / math.sqrt(DT))
        cov_u = np.diag([ODO_VAR_PER_M * ds, GYRO_DENSITY**2 * DT])
        x, P = predict(x, P, ds_m, gyro * DT, cov_u, DT, GYRO_RW**2 * DT)
        if k % 10 == 0:
            z = truth[2] + rng.normal(0, COMPASS_SIGMA)
            x, P = update(x, P, [z], [[COMPASS_SIGMA**2]], HEADING_H, [x[2]], (0,))
        if landmarks and k % 20 == 0:
            lm = LANDMARKS[(k // 20) % 4]
            d = lm - truth[:2]
            z = [
                math.hypot(*d) + rng.normal(0, RANGE_SIGMA),
                wrap_angle(math.atan2(d[1], d[0]) - truth[2] + rng.normal(0, BEARING_SIGMA)),
            ]
            hx, H = landmark_model(x, lm)
            x, P = update(x, P, z, np.diag([RANGE_SIGMA**2, BEARING_SIGMA**2]), H, hx, (1,))
        T.append(truth)
        E.append(x)
        C.append(P)
    return np.array(T), np.array(E), np.array(C)


@pytest.mark.parametrize("landmarks", [True, False])
def test_ekf_is_consistent_on_a_synthetic_trajectory(landmarks: bool) -> None:
    """Average NEES of (x, y, theta) over Monte-Carlo runs stays inside its chi-square interval
    (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2) at every checkpoint; RMSE is bounded."""
    runs, steps = 20, 1200
    nees = np.zeros((runs, steps))
    sq = np.zeros((runs, steps))
    for i in range(runs):
        T, E, C = synthetic_run(100 + i, steps, landmarks)
        e = E[:, :3] - T[:, :3]
        e[:, 2] = wrap_angle(e[:, 2])
        nees[i] = np.einsum("ki,kij,kj->k", e, np.linalg.inv(C[:, :3, :3]), e)
        sq[i] = e[:, 0] ** 2 + e[:, 1] ** 2
    lo, hi = chi2.ppf([0.0005, 0.9995], runs * 3) / runs
    checkpoints = range(99, steps, 100)
    anees = [float(nees[:, k].mean()) for k in checkpoints]
    assert all(lo <= a <= hi for a in anees), (lo, hi, anees)
    rmse = math.sqrt(sq.mean())
    assert rmse < (0.03 if landmarks else 0.05), rmse


def test_tracker_gates_a_misrecognised_landmark_and_counts_it() -> None:
    trk = PoseTracker(PoseTrackerParams(wheel_base_m=0.285, ticks_per_metre=90284.0))
    trk.reset(1.0, 1.0, 0.0, np.diag([1e-4, 1e-4, 1e-3]))
    lm = LANDMARKS[1]
    d = lm - np.array([1.0, 1.0])
    rng, brg = math.hypot(*d), math.atan2(d[1], d[0])
    assert trk.on_landmark(0.0, lm, rng, brg, 0.03, 0.03)
    # the same measurement attributed to the wrong landmark id: far outside the gate
    assert not trk.on_landmark(0.0, LANDMARKS[3], rng, brg, 0.03, 0.03)
    assert trk.counters.accepted == {"landmark": 1} and trk.counters.rejected == {"landmark": 1}


def test_tracker_integrates_ticks_and_gyro_and_falls_back_to_odometry() -> None:
    p = PoseTrackerParams(wheel_base_m=0.285, ticks_per_metre=90284.0)
    trk = PoseTracker(p)
    trk.reset(0.5, 0.5, 0.0, np.diag([1e-4, 1e-4, 1e-4]), gyro_bias=0.02)
    # 1 s straight at 0.1 m/s; the gyro at 100 Hz reads only its known 0.02 rad/s bias
    trk.on_odometry(0.0, 0, 0)
    for k in range(1, 101):
        t = k * 0.01
        trk.on_gyro(t, 0.02)
        left = right = round(k * 0.001 * p.ticks_per_metre)
        trk.on_odometry(t, left, right)
    x, y, th = trk.pose
    assert x == pytest.approx(0.6, abs=1e-5) and y == pytest.approx(0.5, abs=1e-9)
    assert th == pytest.approx(0.0, abs=1e-9)
    # gyro silent for longer than the timeout: the encoders carry the heading (turn on the spot)
    t = 2.0
    d = round(0.285 / 2 * (math.pi / 2) * p.ticks_per_metre)
    trk.on_odometry(t, left - d, right + d)
    assert trk.pose[2] == pytest.approx(math.pi / 2, abs=1e-3)
    assert trk.pose_cov.shape == (3, 3)


def test_tracker_coordinate_fix_moves_only_that_coordinate() -> None:
    trk = PoseTracker(PoseTrackerParams(wheel_base_m=0.285, ticks_per_metre=90284.0))
    trk.reset(1.0, 1.0, 0.0, np.diag([0.02**2, 0.02**2, 1e-4]))
    assert trk.on_coordinate(0.0, 1, 1.03, 0.02)
    x, y, _ = trk.pose
    assert x == pytest.approx(1.0) and y == pytest.approx(1.015)
    assert trk.pose_cov[1, 1] == pytest.approx(0.5 * 0.02**2)
    assert not trk.on_coordinate(0.0, 0, 2.0, 0.01)  # 50 sigma away: gated
