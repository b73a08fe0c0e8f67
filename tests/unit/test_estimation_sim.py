"""Pose tracking against the simulator with every seed error model on, in each lab world.

The robot tours the world's cells in the lab's coverage order, steered on its *true* pose (tour
and steering shared with tests/_localisation_sim.py), so that the measurement is of the
estimator alone; the pose tracker sees only what the buses carry (encoder ticks, gyro rate,
magnetometer field, camera landmarks). It starts from the world's known start pose and first
turns once on the spot ("Find Landmarks", seeds/003 H), which also gives the magnetometer's
hard-iron offset (the centre of the circle the horizontal field draws).

``python tests/unit/test_estimation_sim.py --seconds 300`` prints the 5-minute table of
docs/localisation.md; the test runs 40 s per world.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np
import pytest
from _localisation_sim import WORLDS, coverage_cells, wheel_command, world_config
from koala_bridge.core.geometry import circle_centre, wrap_angle
from koala_bridge.estimation import PoseTracker, PoseTrackerParams, heading_from_field
from koala_bridge.sim.types import WheelCommand

# Position RMSE bounds over the run (docs/localisation.md, "Pose tracking").
RMSE_BOUND_M = {"landmarks": 0.05, "no_landmarks": 0.10}


def sim_config(world: str, seed_models: bool = True) -> dict[str, Any]:
    d = world_config(world)
    if seed_models:
        for name, sec in d["sensors"].items():
            if name != "encoders":  # encoders count the commanded rotation; drive error is below
                sec["ideal"] = False
        d["robot"]["drive_error"]["ideal"] = False
    return d


def camera_sigmas(range_m: float) -> tuple[float, float]:
    """Range and bearing sigmas of a camera landmark (config/default.toml [sensors.camera]:
    5 % at d_mid = 1 m, doubling every metre beyond; 2 deg)."""
    return 0.02 + 0.05 * range_m * 2.0 ** max(0.0, range_m - 1.0), math.radians(2.0)


def run_tracking(world_name: str, seconds: float, seed: int) -> dict[str, float]:
    """Position/heading RMSE of two trackers fed from one simulated run: with and without
    landmark observations."""
    from koala_bridge.sim.models import ERROR_MODELS
    from koala_bridge.sim.simulator import Simulator

    cfg = sim_config(world_name)
    sim = Simulator(cfg, ERROR_MODELS)
    world = sim.world
    robot = cfg["robot"]
    params = PoseTrackerParams(
        wheel_base_m=robot["wheel_base_m"], ticks_per_metre=robot["ticks_per_metre"],
        compass_sigma_rad=math.radians(3.0),
    )
    north = math.radians(world.earth_field.north_deg)
    landmarks = {lm.id: (lm.x, lm.y) for lm in world.landmarks}
    trackers = {"landmarks": PoseTracker(params), "no_landmarks": PoseTracker(params)}
    r = sim.reset(seed=seed)
    assert world.start is not None
    for trk in trackers.values():
        trk.reset(world.start.x, world.start.y, world.start.theta,
                  np.diag([0.01**2, 0.01**2, math.radians(2) ** 2]))
    vmax = robot["max_wheel_speed_mps"] * 0.25
    tour = coverage_cells(world, world.cell_of(world.start.x, world.start.y))
    goals = [world.cell_centre(*c) for c in tour]
    gi = 0
    fields: list[np.ndarray] = []
    hard_iron: np.ndarray | None = None
    spin_until = 2 * math.pi / 1.0 + 1.0  # one turn at 1 rad/s
    err2: dict[str, list[float]] = {k: [] for k in trackers}
    herr2: dict[str, list[float]] = {k: [] for k in trackers}
    steps = int(seconds / sim.dt)
    for _ in range(steps):
        t = r.t
        for name, trk in trackers.items():
            if r.gyro is not None:
                trk.on_gyro(t, r.gyro.yaw_rate)
            if r.odometry is not None:
                trk.on_odometry(t, r.odometry.left_ticks, r.odometry.right_ticks)
            if r.compass is not None and hard_iron is not None:
                hard = np.array([hard_iron[0], hard_iron[1], 0.0])
                trk.on_compass(t, heading_from_field(r.compass.field_uT, north, hard))
            if r.camera is not None and name == "landmarks":
                for ob in r.camera.observations:
                    if ob.id in landmarks:
                        sr, sb = camera_sigmas(ob.range)
                        trk.on_landmark(t, landmarks[ob.id], ob.range, ob.bearing, sr, sb)
            ex, ey, eth = trk.pose
            err2[name].append((ex - r.pose.x) ** 2 + (ey - r.pose.y) ** 2)
            herr2[name].append(wrap_angle(eth - r.pose.theta) ** 2)
        if t < spin_until:
            if r.compass is not None:
                fields.append(r.compass.field_uT[:2].copy())
            cmd = WheelCommand(-0.5 * robot["wheel_base_m"], 0.5 * robot["wheel_base_m"])
        else:
            if hard_iron is None:
                hard_iron = circle_centre(np.array(fields))
            goal = goals[gi]
            if math.hypot(goal[0] - r.pose.x, goal[1] - r.pose.y) < 0.03:
                gi = (gi + 1) % len(goals)
                if gi == 0:
                    goals = goals[::-1]  # tour back and forth
                goal = goals[gi]
            cmd = wheel_command(r.pose, goal, robot["wheel_base_m"], vmax)
        r = sim.step(cmd)
    out = {}
    for name in trackers:
        out[f"{name}_rmse_m"] = math.sqrt(float(np.mean(err2[name])))
        out[f"{name}_heading_rmse_deg"] = math.degrees(math.sqrt(float(np.mean(herr2[name]))))
        out[f"{name}_rejected"] = float(sum(trackers[name].counters.rejected.values()))
    return out


@pytest.mark.parametrize("world", WORLDS)
def test_pose_tracking_rmse_with_seed_error_models(world: str) -> None:
    res = run_tracking(world, seconds=40.0, seed=7)
    assert res["landmarks_rmse_m"] < RMSE_BOUND_M["landmarks"], res
    assert res["no_landmarks_rmse_m"] < RMSE_BOUND_M["no_landmarks"], res


def main() -> None:
    ap = argparse.ArgumentParser(description="pose-tracking RMSE table per lab world")
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    for world in WORLDS:
        rows = [run_tracking(world, args.seconds, seed) for seed in range(args.seeds)]
        mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        worst = {k: float(np.max([r[k] for r in rows])) for k in rows[0]}
        print(f"{world:18s} with landmarks: {mean['landmarks_rmse_m'] * 100:5.1f} cm "
              f"(worst {worst['landmarks_rmse_m'] * 100:5.1f}), heading "
              f"{mean['landmarks_heading_rmse_deg']:4.1f} deg | without: "
              f"{mean['no_landmarks_rmse_m'] * 100:5.1f} cm (worst "
              f"{worst['no_landmarks_rmse_m'] * 100:5.1f}), heading "
              f"{mean['no_landmarks_heading_rmse_deg']:4.1f} deg | gated out "
              f"{mean['landmarks_rejected']:.0f}")


if __name__ == "__main__":
    main()
