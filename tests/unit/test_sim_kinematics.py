"""Differential-drive kinematics and wall collisions (sim/robot.py, sim/simulator.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _sim_support import box_world, config_with_world
from koala_bridge.core.raycast import SegmentSet
from koala_bridge.sim import robot as kin
from koala_bridge.sim.config import load_sim_config
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand


def make_sim(**world_kw: object) -> Simulator:
    return Simulator(config_with_world(box_world(**world_kw), ideal=True))


def drive(sim: Simulator, left: float, right: float, seconds: float):
    r = None
    for _ in range(round(seconds / sim.dt)):
        r = sim.step(WheelCommand(left, right))
    return r


def test_straight_line_distance() -> None:
    sim = make_sim(x=1.0, y=3.0)
    sim.reset(0)
    r = drive(sim, 0.2, 0.2, 5.0)
    assert r.pose.x == pytest.approx(2.0, abs=1e-9)
    assert r.pose.y == pytest.approx(3.0, abs=1e-12)
    assert r.pose.theta == pytest.approx(0.0, abs=1e-12)
    assert not r.collided


def test_turn_in_place_angle() -> None:
    sim = make_sim()
    sim.reset(0)
    b = sim.config.robot.wheel_base_m
    v = 0.1
    r = drive(sim, -v, v, 1.0)
    assert r.pose.theta == pytest.approx(2 * v / b * 1.0, abs=1e-12)
    assert (r.pose.x, r.pose.y) == pytest.approx((3.0, 3.0), abs=1e-12)
    # A full turn and a bit more wraps to (-pi, pi].
    r = drive(sim, -v, v, 9.0)
    assert -math.pi < r.pose.theta <= math.pi
    assert r.pose.theta == pytest.approx(kin.wrap_angle(2 * v / b * 10.0), abs=1e-9)


def test_arc_follows_the_circle() -> None:
    sim = make_sim()
    sim.reset(0)
    b = sim.config.robot.wheel_base_m
    vl, vr = 0.1, 0.2
    v, w = (vl + vr) / 2, (vr - vl) / b
    T = 3.0
    r = drive(sim, vl, vr, T)
    # Exact circle from (3, 3) heading east: centre (3, 3 + v/w).
    R = v / w
    assert r.pose.x == pytest.approx(3.0 + R * math.sin(w * T), abs=1e-9)
    assert r.pose.y == pytest.approx(3.0 + R - R * math.cos(w * T), abs=1e-9)
    assert r.pose.theta == pytest.approx(w * T, abs=1e-9)


def test_exact_arc_is_independent_of_dt() -> None:
    params = load_sim_config(config_with_world(box_world(), ideal=True)).robot
    walls = SegmentSet.from_segments(np.zeros((0, 4)))
    a = kin.RobotState.at(0, 0, 0.3)
    for _ in range(100):
        a = kin.step(a, 0.13, 0.31, 0.01, params, walls)
    b = kin.step(kin.RobotState.at(0, 0, 0.3), 0.13, 0.31, 1.0, params, walls)
    assert (a.x, a.y, a.heading) == pytest.approx((b.x, b.y, b.heading), abs=1e-12)


def test_wheel_speed_limit() -> None:
    sim = make_sim(x=1.0)
    sim.reset(0)
    vmax = sim.config.robot.max_wheel_speed_mps
    r = sim.step(WheelCommand(10.0, -10.0))
    assert (r.wheel_speeds.left, r.wheel_speeds.right) == pytest.approx((vmax, -vmax))
    r = sim.step(WheelCommand(float("nan"), 0.0))
    assert r.wheel_speeds.left == 0.0


def test_wall_stops_the_robot_and_reports_collision() -> None:
    sim = make_sim(x=5.0, y=3.0)          # east wall at x = 6
    sim.reset(0)
    radius = sim.config.robot.body_radius_m
    vmax = sim.config.robot.max_wheel_speed_mps
    r = drive(sim, vmax, vmax, 3.0)
    assert r.collided
    assert r.pose.x <= 6.0 - radius + 1e-9
    assert r.pose.x == pytest.approx(6.0 - radius, abs=1e-6)
    assert r.wheel_speeds.left == pytest.approx(0.0, abs=1e-6)
    # Backing away is allowed and clears the flag.
    r = sim.step(WheelCommand(-0.1, -0.1))
    assert not r.collided and r.pose.x < 6.0 - radius
    # Turning in place against a wall is allowed (circular body).
    drive(sim, vmax, vmax, 1.0)
    r = sim.step(WheelCommand(-0.2, 0.2))
    assert not r.collided and r.pose.theta > 0


def test_no_tunnelling_through_a_thin_wall_with_a_huge_step() -> None:
    params = load_sim_config(config_with_world(box_world(), ideal=True)).robot
    walls = SegmentSet.from_segments(np.array([[1.0, -1.0, 1.0, 1.0]]))
    s = kin.step(kin.RobotState.at(0.0, 0.0, 0.0), 0.6, 0.6, 10.0, params, walls)  # 6 m in 1 step
    assert s.collided
    assert s.x == pytest.approx(1.0 - params.body_radius_m, abs=1e-6)
    # Wheel travel (encoders) stops with the body.
    assert s.left_travel_m == pytest.approx(s.x, abs=1e-6)


def test_diagonal_corner_approach_stays_outside() -> None:
    sim = make_sim(x=5.0, y=5.0, theta_deg=45.0)
    sim.reset(0)
    r = drive(sim, 0.6, 0.6, 4.0)
    radius = sim.config.robot.body_radius_m
    assert r.collided
    assert r.pose.x <= 6.0 - radius + 1e-9 and r.pose.y <= 6.0 - radius + 1e-9


def test_time_is_step_count_times_dt() -> None:
    sim = make_sim()
    r = sim.reset(0)
    assert r.t == 0.0
    for _ in range(1, 1001):
        r = sim.step(WheelCommand())
    assert r.t == 1000 * sim.dt
    assert sim.step_count == 1000
