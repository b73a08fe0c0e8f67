"""Several robots in one world (sim/fleet.py): each sees the others with its range sensors and
camera, stops on contact with them, and draws from its own seeded streams."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from _sim_support import default_config
from koala_bridge.core.raycast import SegmentSet, circle_polygons, point_segment_distances
from koala_bridge.sim.fleet import Fleet
from koala_bridge.sim.simulator import OBSTACLE_SIDES, Simulator
from koala_bridge.sim.types import WheelCommand

# In the default world's open middle row, facing each other 0.9 m apart (centres).
A_START = (1.3, 1.75, 0.0)
B_START = (2.2, 1.75, 180.0)
FORWARD = WheelCommand(0.3, 0.3)
STILL = WheelCommand(0.0, 0.0)


def _at(x: float, y: float, theta_deg: float) -> Simulator:
    cfg = copy.deepcopy(default_config())
    cfg["world"]["start"] = {"x": x, "y": y, "theta_deg": theta_deg}
    return Simulator(cfg)


def _front_sonar(sim: Simulator) -> int:
    """The sonar whose axis points straight ahead."""
    return int(np.argmin(np.abs([p[2] for p in sim.config.sensors.sonar.poses])))


def test_circumscribed_polygon_touches_the_circle_from_outside() -> None:
    segs = SegmentSet.from_segments(circle_polygons(np.array([[0.5, -0.2, 0.19]]),
                                                    OBSTACLE_SIDES), merge=False)
    d = point_segment_distances(segs, 0.5, -0.2)
    assert d.min() == pytest.approx(0.19, abs=1e-12)    # edges touch at their midpoints
    # the fast path a fleet uses builds the same set as from_segments
    walls = SegmentSet.from_segments(np.array([[0.0, 0.0, 3.0, 0.0], [0.0, 0.0, 0.0, 3.0]]))
    circles = np.array([[0.5, -0.2, 0.19], [2.0, 1.0, 0.25]])
    fast = walls.with_circles(circles, OBSTACLE_SIDES)
    slow = SegmentSet.from_segments(np.concatenate(
        [walls.segments, circle_polygons(circles, OBSTACLE_SIDES)]), merge=False)
    for name in ("segments", "ax", "ay", "ex", "ey", "inv_len", "inv_len2", "packed"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=1e-12,
                                   atol=1e-12)


def test_a_sees_b_with_its_forward_sonar() -> None:
    fleet = Fleet([_at(*A_START), _at(*B_START)])
    a, _b = fleet.reset(seed=5)
    alone = _at(*A_START).reset(seed=5)
    front = _front_sonar(fleet.robots[0])
    sensor_x = fleet.robots[0].config.sensors.sonar.poses[front][0]
    # the ray from A's front sonar ends on B's body: B's centre minus its radius
    expected = (B_START[0] - 0.19) - (A_START[0] + sensor_x)
    assert a.sonar.truth_ranges[front] == pytest.approx(expected, abs=0.19 * 0.02)
    assert alone.sonar.truth_ranges[front] > expected + 0.5      # without B: the far wall


def test_a_drives_into_b_stops_at_contact_and_its_ir_sees_b() -> None:
    fleet = Fleet([_at(*A_START), _at(*B_START)])
    fleet.reset(seed=2)
    sim_a = fleet.robots[0]
    step_m = sim_a.config.robot.max_wheel_speed_mps * fleet.dt
    contact = 2 * 0.19
    collided = False
    for _ in range(400):
        a, b = fleet.step([FORWARD, STILL])
        d = math.hypot(a.pose.x - b.pose.x, a.pose.y - b.pose.y)
        assert d >= contact - step_m          # never through B
        collided = collided or a.collided
    assert collided
    assert d < contact + 0.03                 # pushed on against B: it stays at contact
    # at contact A's front IR sees B; a robot alone at A's pose sees nothing there
    while a.ir is None:
        a, b = fleet.step([STILL, STILL])
    alone = _at(a.pose.x, a.pose.y, math.degrees(a.pose.theta)).reset(seed=2)
    front = int(np.argmin(np.abs([p[2] + 360 * (p[2] < -180) for p in
                                  sim_a.config.sensors.ir.poses])))
    assert np.isfinite(a.ir.truth_ranges[front])
    assert not np.isfinite(alone.ir.truth_ranges[front])
    assert a.ir.truth_counts[front] > alone.ir.truth_counts[front]


def test_the_camera_does_not_see_through_another_robot() -> None:
    # Landmark 4 is dead ahead of A on the east wall; B between them hides it.
    solo = _at(*A_START).reset(seed=1)
    assert 4 in [o.id for o in solo.camera.truth]
    a, _b = Fleet([_at(*A_START), _at(*B_START)]).reset(seed=1)
    assert 4 not in [o.id for o in a.camera.truth]


def _run(seed: int, steps: int = 300) -> list[str]:
    fleet = Fleet([_at(*A_START), _at(*B_START)])
    out = [repr(r) for r in fleet.reset(seed)]
    for k in range(steps):
        out += [repr(r) for r in fleet.step([FORWARD, WheelCommand(0.1, -0.1 if k % 50 else 0.2)])]
    return out


def test_same_seed_same_streams_for_every_robot() -> None:
    first, second = _run(9), _run(9)
    assert first == second
    assert first != _run(10)


def test_each_robot_has_its_own_streams() -> None:
    # Standing still, a gyro reads its bias and noise only: each robot's own child of the seed.
    fleet = Fleet([_at(*A_START), _at(*B_START)], stream_keys=[0, 1])
    a, b = fleet.reset(seed=4)
    assert a.gyro.yaw_rate != b.gyro.yaw_rate
    with pytest.raises(ValueError, match="distinct"):
        Fleet([_at(*A_START), _at(*B_START)], stream_keys=[3, 3])
