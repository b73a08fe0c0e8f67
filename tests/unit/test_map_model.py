"""Range sensors against the known map (bridge/estimation/map_model.py), the particle relocaliser
(relocaliser.py), the health monitor (health.py) and the EKF's gated range update."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.core.raycast import cast_fan_arrays
from koala_bridge.estimation.health import LOST, TRACKING, UNCERTAIN, HealthMonitor, HealthParams
from koala_bridge.estimation.map_model import MapModel
from koala_bridge.estimation.pose_filter import PoseTracker, PoseTrackerParams
from koala_bridge.estimation.relocaliser import Relocaliser, RelocaliserParams
from koala_bridge.sim.config import load_sim_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def robot():
    return load_sim_config(tomllib.loads((ROOT / "config" / "default.toml").read_text()))


@pytest.fixture(scope="module")
def model(robot):
    return MapModel(robot.world)


def _ir_rays(robot) -> np.ndarray:
    p = np.asarray(robot.sensors.ir.poses, dtype=float)   # radians
    return np.ascontiguousarray(p.T.copy())


def test_expected_range_jacobian_matches_finite_differences(robot, model) -> None:
    rays = _ir_rays(robot)
    far = np.full(rays.shape[1], 3.0)
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(40):
        pose = (rng.uniform(0.3, 2.7), rng.uniform(0.3, 2.7), rng.uniform(-math.pi, math.pi))
        hits = model.expected(pose, rays, far)
        for i, h in enumerate(hits):
            if h is None or not math.isfinite(h.r):
                continue
            for k in range(3):
                p = list(pose)
                p[k] += 1e-6
                h2 = model.expected(tuple(p), rays, far)[i]
                if h2 is None or not math.isfinite(h2.r) or abs(h2.r - h.r) > 1e-3:
                    continue  # the nudge crossed onto another wall
                assert (h2.r - h.r) / 1e-6 == pytest.approx(h.H[k], abs=1e-3)
                checked += 1
    assert checked > 500


def test_expected_range_equals_the_simulators_cast(robot, model) -> None:
    rays = _ir_rays(robot)
    far = np.full(rays.shape[1], 3.0)
    pose = (1.75, 1.75, 0.3)
    out, _ = cast_fan_arrays(model.walls, rays, far, *pose)
    for i, h in enumerate(model.expected(pose, rays, far)):
        if h is not None:
            assert h.r == out[4, i]


def test_nothing_in_range_is_infinite_and_a_corner_hit_is_not_used(robot) -> None:
    model = MapModel(robot.world, corner_margin_m=0.03)
    one = np.ascontiguousarray(np.array([[0.0], [0.0], [0.0]]))
    # facing east from the middle with a 0.1 m range: nothing there
    (h,) = model.expected((1.75, 1.75, 0.0), one, np.array([0.1]))
    assert h is not None and h.r == math.inf
    # aimed exactly at the north-east corner (3, 3): the hit is at a wall's end
    (h,) = model.expected((2.5, 2.5, math.pi / 4), one, np.array([2.0]))
    assert h is None


def test_distance_field_is_the_distance_to_the_nearest_wall(model) -> None:
    # the open middle of the default arena: the nearest walls are the inner walls
    xs = np.array([0.25, 1.75, 2.9])
    ys = np.array([0.25, 2.9, 1.75])
    d = model.distance(xs, ys)
    assert d[0] == pytest.approx(0.25, abs=0.011)     # 0.25 from the west and south walls
    assert d[1] == pytest.approx(0.1, abs=0.011)      # 0.1 below the north wall
    assert d[2] == pytest.approx(0.1, abs=0.011)      # 0.1 from the east wall
    assert model.distance(np.array([-0.5]), np.array([1.0]))[0] == pytest.approx(0.5, abs=0.011)


def test_range_update_gates_an_outlier_and_fuses_the_rest() -> None:
    tr = PoseTracker(PoseTrackerParams(wheel_base_m=0.3, ticks_per_metre=1000.0))
    tr.reset(1.0, 1.0, 0.0, np.diag([0.02**2, 0.02**2, 0.01]))
    # two readings of a wall at x = 2 straight ahead (dr/dx = -1): one 1 cm long, one 0.5 m long
    ok = tr.on_ranges(0.0, "ir", [1.01, 1.5], [1.0, 1.0], [[-1, 0, 0], [-1, 0, 0]],
                      [0.01, 0.01])
    assert ok.tolist() == [True, False]
    assert tr.x[0] < 1.0 and tr.x[0] == pytest.approx(1.0 - 0.01 * 0.02**2 / (0.02**2 + 0.01**2))
    assert tr.counters.rejected["ir"] == 1


def test_relocaliser_finds_the_robot_from_ranges_landmarks_and_compass(robot, model) -> None:
    """From particles spread over the whole map, noise-free readings at the true pose make the
    cloud converge on it (the default arena is not symmetric once the landmarks are used)."""
    truth = (0.8, 2.2, 0.5)
    rel = Relocaliser(model, RelocaliserParams(particles=3000, body_radius_m=0.19), seed=2)
    rel.start(2.0, 0.8, truth[2], heading=truth[2])     # the last estimate: far away
    body = np.asarray(robot.sensors.sonar.poses, dtype=float)
    rays = np.ascontiguousarray(body.T.copy())
    far = np.full(len(body), 2.5)
    out, _ = cast_fan_arrays(model.walls, rays, far, *truth)
    ranges = out[4]
    sig = np.full(len(body), 0.02)
    landmarks = [(lm.x, lm.y) for lm in robot.world.landmarks]
    for step in range(40):
        rel.on_ranges(body, ranges, sig)
        rel.on_heading(truth[2], math.radians(5))
        lx, ly = landmarks[step % len(landmarks)]
        dx, dy = lx - truth[0], ly - truth[1]
        rel.on_landmark(lx, ly, math.hypot(dx, dy), math.atan2(dy, dx) - truth[2], 0.05, 0.05)
        rel.predict(0.0, 0.0, 0.002, 0.002)
    mean, cov = rel.estimate()
    assert rel.converged
    assert math.hypot(mean[0] - truth[0], mean[1] - truth[1]) < 0.1
    assert abs(mean[2] - truth[2]) < math.radians(5)


def test_health_states() -> None:
    h = HealthMonitor(HealthParams(window_s=2.0, lost_min_rejections=8, lost_reject_ratio=0.7,
                                   no_fix_timeout_s=10.0))
    h.reset(0.0)
    h.evidence(0.5, accepted=10, rejected=1)
    assert h.assess(1.0, 0.01, 0.01, False, False) == (TRACKING, [])
    assert h.assess(1.0, 0.01, 0.01, True, True) == (UNCERTAIN, ["wheel_slip", "wall_contact"])
    assert h.assess(1.0, 0.5, 0.01, False, False) == (UNCERTAIN, ["covariance_large"])
    assert h.assess(11.0, 0.01, 0.01, False, False) == (UNCERTAIN, ["no_absolute_fix"])
    # 7 rejections are not enough; 9 of 9 in the window are; the old acceptances expired
    h.evidence(3.0, 0, 7)
    assert h.inconsistent(3.0) == []
    h.evidence(3.5, 0, 2)
    assert h.assess(3.5, 0.01, 0.01, False, False) == (LOST, ["innovations_rejected"])
    # a body in the wall for in_wall_s
    h.reset(4.0)
    h.body_in_wall(4.0, True)
    assert h.inconsistent(4.2) == []
    assert h.inconsistent(4.6) == ["estimate_in_wall"]


def test_disputed_evidence_is_uncertain_not_lost() -> None:
    h = HealthMonitor(HealthParams(window_s=2.0, lost_min_rejections=8, lost_reject_ratio=0.7,
                                   disputed_ratio=0.3, no_fix_timeout_s=10.0))
    h.reset(0.0)
    h.evidence(0.5, accepted=20, rejected=7)      # 7 rejected: under lost_min_rejections
    assert h.assess(0.5, 0.01, 0.01, False, False) == (TRACKING, [])
    h.evidence(0.6, accepted=0, rejected=2)       # 9 of 29 = 31 %: disputed, far from 70 %
    assert h.assess(0.6, 0.01, 0.01, False, False) == (UNCERTAIN, ["evidence_disputed"])
    h.evidence(0.7, accepted=10, rejected=0)      # 9 of 39 = 23 %: tracking again
    assert h.assess(0.7, 0.01, 0.01, False, False) == (TRACKING, [])


def test_nearest_wall_is_exact_and_points_away_from_it(model) -> None:
    # 0.1 m below the default arena's north wall (y = 3), in the open
    d, gx, gy = model.nearest_wall(1.75, 2.9)
    assert d == pytest.approx(0.1, abs=1e-12)
    assert (gx, gy) == pytest.approx((0.0, -1.0), abs=1e-12)
    # agrees with the rasterised distance field to its resolution everywhere in the arena
    rng = np.random.default_rng(5)
    for x, y in rng.uniform(0.05, 2.95, size=(200, 2)):
        d, gx, gy = model.nearest_wall(float(x), float(y))
        assert d == pytest.approx(float(model.distance(np.array([x]), np.array([y]))[0]),
                                  abs=0.011)
        assert math.hypot(gx, gy) == pytest.approx(1.0)
        # a step along the direction moves away from the nearest wall by that step
        d2, _, _ = model.nearest_wall(float(x + 1e-4 * gx), float(y + 1e-4 * gy))
        assert d2 >= d + 1e-4 - 1e-9 or d2 == pytest.approx(d + 1e-4, abs=1e-9)
