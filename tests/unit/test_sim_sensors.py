"""Ideal sensors against geometry (sim/sensors/*, bridge/core/raycast.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _sim_support import box_world, config_with_world, ideal_config
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.core.raycast import SegmentSet, cast_rays, first_hit_before, merge_collinear
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand


def make_sim(world: dict) -> Simulator:
    return Simulator(config_with_world(world, ideal=True))


# ---------------------------------------------------------------------- raycast
def test_raycast_range_index_incidence() -> None:
    walls = SegmentSet.from_segments(np.array([[2.0, -1.0, 2.0, 1.0], [0.0, 3.0, 4.0, 3.0]]),
                                     merge=False)
    a = np.radians([0.0, 20.0, 90.0, 180.0])
    hits = cast_rays(walls, np.zeros(4), np.zeros(4), np.cos(a), np.sin(a))
    assert hits.range[0] == pytest.approx(2.0)
    assert hits.index[0] == 0 and hits.incidence[0] == pytest.approx(0.0)
    assert hits.range[1] == pytest.approx(2.0 / math.cos(math.radians(20)))
    assert hits.incidence[1] == pytest.approx(math.radians(20))
    assert hits.range[2] == pytest.approx(3.0) and hits.index[2] == 1
    assert hits.incidence[2] == pytest.approx(0.0, abs=1e-12)
    assert math.isinf(hits.range[3]) and hits.index[3] == -1 and math.isnan(hits.incidence[3])
    short = cast_rays(walls, np.zeros(4), np.zeros(4), np.cos(a), np.sin(a), max_range=2.5)
    assert short.index.tolist() == [0, 0, -1, -1]


def test_merge_collinear_keeps_geometry() -> None:
    segs = np.array([[0, 0, 1, 0], [1, 0, 2, 0], [3, 0, 4, 0], [0, 0, 0, 1], [0, 1, 0, 2],
                     [0, 0, 1, 1]], dtype=float)
    merged = merge_collinear(segs)
    assert len(merged) == 4
    walls_a = SegmentSet.from_segments(segs, merge=False)
    walls_b = SegmentSet.from_segments(segs, merge=True)
    rng = np.random.default_rng(3)
    ox, oy = rng.uniform(-1, 5, 200), rng.uniform(-1, 3, 200)
    a = rng.uniform(-np.pi, np.pi, 200)
    ra = cast_rays(walls_a, ox, oy, np.cos(a), np.sin(a)).range
    rb = cast_rays(walls_b, ox, oy, np.cos(a), np.sin(a)).range
    np.testing.assert_allclose(ra, rb)


def test_line_of_sight() -> None:
    walls = SegmentSet.from_segments(np.array([[1.0, -1.0, 1.0, 1.0]]))
    blocked = first_hit_before(walls, np.zeros(2), np.zeros(2), np.array([2.0, 0.5]),
                               np.array([0.0, 0.0]))
    assert blocked.tolist() == [True, False]


# ---------------------------------------------------------------------- sonar
def test_sonar_ranges_match_geometry() -> None:
    sim = make_sim(box_world(x=4.0, y=3.0))        # east wall at x = 6, robot facing east
    r = sim.reset(0)
    poses = sim.config.sensors.sonar.poses
    front = int(np.argmin(np.abs(poses[:, 2]) + np.abs(poses[:, 1])))
    expected = 6.0 - 4.0 - poses[front, 0]
    assert r.sonar.ranges[front] == pytest.approx(expected, abs=1e-9)
    assert r.sonar.truth_ranges[front] == pytest.approx(expected, abs=1e-9)
    assert r.sonar.incidence[front] == pytest.approx(0.0, abs=1e-9)
    # Each sensor: first echo of its cone = min over rays, computed independently here.
    sp = sim.config.sensors.sonar
    half = math.radians(sp.aperture_deg) / 2
    walls = SegmentSet.from_segments(sim.world.segments)
    for i, (bx, by, bt) in enumerate(poses):
        a = bt + np.linspace(-half, half, sp.rays)
        h = cast_rays(walls, np.full(sp.rays, 4.0 + bx), np.full(sp.rays, 3.0 + by),
                      np.cos(a), np.sin(a), sp.max_range_m)
        m = h.range.min()
        if np.isinf(m):
            assert math.isnan(r.sonar.ranges[i])
        else:
            assert r.sonar.truth_ranges[i] == pytest.approx(m)


def test_sonar_too_close_reads_zero_and_far_reads_no_echo() -> None:
    sp_front = 0.19
    sim = make_sim(box_world(x=6.0 - sp_front - 0.2, y=3.0))   # 0.2 m < min range 0.25 m
    r = sim.reset(0)
    poses = sim.config.sensors.sonar.poses
    front = int(np.argmin(np.abs(poses[:, 2]) + np.abs(poses[:, 1])))
    assert r.sonar.ranges[front] == 0.0
    assert r.sonar.truth_ranges[front] == pytest.approx(0.2, abs=1e-9)
    big = make_sim(box_world(cols=20, rows=20, x=5.0, y=5.0))   # 10 m box: nothing in 2.5 m
    assert np.all(np.isnan(big.reset(0).sonar.ranges))


# ---------------------------------------------------------------------- IR
def test_ir_counts_rise_approaching_a_wall() -> None:
    sim = make_sim(box_world(x=5.0, y=3.0))    # east wall at 6 m
    sim.reset(0)
    front = [0, 15]                             # the two sensors looking (almost) forward
    history = []
    for _ in range(1000):
        r = sim.step(WheelCommand(0.1, 0.1))
        if r.ir is not None:
            history.append(r.ir.counts[front].copy())
        if r.collided:
            break
    h = np.array(history)
    assert h[0].max() == 0                                  # 0.63 m away: out of IR range
    assert np.all(np.diff(h, axis=0) >= 0)                  # never falls while approaching
    assert h[-1].min() > 500                                # touching the wall: near saturation
    assert r.ir.ambient.shape == (16,)


def test_ir_truth_range_along_axis() -> None:
    sim = make_sim(box_world(x=6.0 - 0.175 - 0.05, y=3.0))  # sensor 0/15 tips 5 cm from the wall
    r = sim.reset(0)
    ax_range = r.ir.truth_ranges[0]
    assert ax_range == pytest.approx(0.05 / math.cos(math.radians(5.7)), rel=1e-3)
    ip = sim.config.sensors.ir
    assert r.ir.counts[0] == pytest.approx(np.interp(ax_range, ip.response_range_m,
                                                     ip.response_counts), abs=5)


# ---------------------------------------------------------------------- encoders and gyro
def test_encoder_ticks_equal_distance_times_ticks_per_metre() -> None:
    sim = make_sim(box_world(x=1.0, y=3.0))
    sim.reset(0)
    tpm = sim.config.robot.ticks_per_metre
    for _ in range(250):
        r = sim.step(WheelCommand(0.2, 0.2))
    assert r.odometry.left_ticks == round(0.5 * tpm)
    assert r.odometry.right_ticks == round(0.5 * tpm)
    for _ in range(100):
        r = sim.step(WheelCommand(-0.1, 0.1))
    assert r.odometry.left_ticks == round(0.4 * tpm)
    assert r.odometry.right_ticks == round(0.6 * tpm)


def test_integrated_gyro_equals_heading_change() -> None:
    sim = make_sim(box_world())
    r0 = sim.reset(0)
    rng = np.random.default_rng(1)
    integral = 0.0
    last_t = 0.0
    heading = r0.pose.theta
    unwrapped = 0.0
    for _ in range(60):
        cmd = WheelCommand(*rng.uniform(-0.3, 0.3, 2))
        for _ in range(rng.integers(1, 9)):
            r = sim.step(cmd)
            d = r.pose.theta - heading
            unwrapped += wrap_angle(d)
            heading = r.pose.theta
            if r.gyro is not None:
                integral += r.gyro.yaw_rate * (r.t - last_t)
                last_t = r.t
                assert r.gyro.yaw_rate == r.gyro.truth_yaw_rate
    assert abs(unwrapped) > 0.05
    assert integral == pytest.approx(unwrapped, abs=1e-9)


# ---------------------------------------------------------------------- compass
@pytest.mark.parametrize("theta_deg", [0.0, 37.0, 90.0, 179.0, -120.0])
def test_compass_heading_matches_truth_without_local_sources(theta_deg: float) -> None:
    world = box_world(theta_deg=theta_deg,
                      earth_field={"horizontal_uT": 20.0, "vertical_uT": -43.0, "north_deg": 90.0})
    r = make_sim(world).reset(0)
    bx, by, bz = r.compass.field_uT
    heading_cw_from_north = math.atan2(by, bx)         # FLU: field to the left = heading east
    theta = math.radians(90.0) - heading_cw_from_north  # CCW from east
    err = wrap_angle(theta - math.radians(theta_deg))
    assert err == pytest.approx(0, abs=1e-12)
    assert bz == -43.0
    assert math.hypot(bx, by) == pytest.approx(20.0)


def test_compass_local_source_falls_with_distance_squared() -> None:
    base = {"horizontal_uT": 0.0, "vertical_uT": 0.0, "north_deg": 90.0}
    for d in (0.5, 1.0, 2.0):
        world = box_world(x=3.0, y=3.0, earth_field=base,
                          magnetic_sources=[{"x": 3.0 + d, "y": 3.0, "strength_uT": 4.0}])
        r = make_sim(world).reset(0)
        # Facing east, source straight ahead: field along +x body, magnitude 4 / d^2.
        assert r.compass.field_uT == pytest.approx([4.0 / d**2, 0.0, 0.0])


# ---------------------------------------------------------------------- camera
def _camera_world(**extra: object) -> dict:
    lm = [{"id": 7, "colour": "red", "x": 4.5, "y": 3.0}, {"id": 8, "colour": "blue", "x": 3.0,
                                                             "y": 5.0}]
    return box_world(x=3.0, y=3.0, landmarks=lm, **extra)


def test_camera_sees_landmarks_in_view() -> None:
    r = make_sim(_camera_world()).reset(0)
    assert [o.id for o in r.camera.observations] == [7]      # 8 is 90 deg left, outside 60 deg
    o = r.camera.observations[0]
    assert o.range == pytest.approx(1.5) and o.bearing == pytest.approx(0.0)
    assert r.camera.truth == r.camera.observations


def test_camera_occlusion_by_a_wall() -> None:
    # A wall on the west side of cell (8, 6) at x = 4.0 between the robot and landmark 7.
    r = make_sim(_camera_world(walls=[[8, 6, "W"], [8, 5, "W"]])).reset(0)
    assert r.camera.observations == ()


def test_camera_bearing_sign() -> None:
    r = make_sim(_camera_world(start={"x": 3.0, "y": 3.0, "theta_deg": 70.0})).reset(0)
    ids = {o.id: o for o in r.camera.observations}
    assert set(ids) == {8}
    assert ids[8].bearing == pytest.approx(math.radians(20.0))   # landmark left of heading: CCW +


def test_camera_sees_a_landmark_from_the_default_start_pose() -> None:
    # A run nobody drives must still exercise landmark observations (config/default.toml).
    r = Simulator(ideal_config()).reset(0)
    assert [o.id for o in r.camera.truth] == [4]
    assert r.camera.truth[0].range == pytest.approx(1.2)
    assert r.camera.truth[0].bearing == pytest.approx(0.0, abs=1e-9)


def test_compiled_cast_matches_numpy_reference() -> None:
    from koala_bridge.core.raycast import cast_fan, cast_rays_numpy
    from koala_bridge.sim.sensors.fan import RayFan

    rng = np.random.default_rng(7)
    segs = np.concatenate([rng.uniform(0, 4, (30, 4)),
                           np.array([[0, 0, 4, 0], [4, 0, 4, 4], [4, 4, 0, 4], [0, 4, 0, 0.0]])])
    walls = SegmentSet.from_segments(segs)
    n = 500
    ox, oy = rng.uniform(0.1, 3.9, n), rng.uniform(0.1, 3.9, n)
    a = rng.uniform(-np.pi, np.pi, n)
    mr = rng.uniform(0.1, 6.0, n)
    fast = cast_rays(walls, ox, oy, np.cos(a), np.sin(a), mr)
    ref = cast_rays_numpy(walls, ox, oy, np.cos(a), np.sin(a), mr)
    np.testing.assert_allclose(fast.range, ref.range, rtol=1e-12)
    np.testing.assert_array_equal(fast.index, ref.index)
    np.testing.assert_allclose(fast.incidence, ref.incidence, rtol=1e-9, atol=1e-12)
    # The body-frame fan cast equals casting its world rays.
    poses = np.column_stack([rng.uniform(-0.2, 0.2, 12), rng.uniform(-0.2, 0.2, 12),
                             rng.uniform(-np.pi, np.pi, 12)])
    fan = RayFan.build(poses, 5, 0.4)
    hits, rays = cast_fan(walls, fan.body, np.full(fan.size, 2.5), 2.0, 1.5, 0.7)
    ox, oy, dx, dy = fan.world_rays(2.0, 1.5, 0.7)
    np.testing.assert_allclose(rays, np.stack([ox, oy, dx, dy]), atol=1e-15)
    ref = cast_rays_numpy(walls, ox, oy, dx, dy, 2.5)
    np.testing.assert_allclose(hits.range, ref.range, rtol=1e-12)
    np.testing.assert_array_equal(hits.index, ref.index)
