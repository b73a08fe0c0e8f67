"""Issue 3, "done when", over Zenoh: a bridge subprocess (fast clock) with every error model on
publishes sensor values that differ from their ``truth`` companions the way docs/models.md says;
with every model off (config/ideal.toml) every message's measurement equals its truth.

The robot stands still at ``POSE``: by the south wall (IR sensors see it), with the magnetic
source of the default world close by, facing landmark 3. At rest the gyro's truth is 0 and the
compass model reduces to ``S B + b_hard + n`` (no motor current), so the statistics below need
no knowledge of the motion. Model parameters are read from the config file the bridge ran on;
the geometry (IR axis ranges and incidence, camera field of view) is recomputed here from the
``world`` answer with an independent ray/segment intersection.
"""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial
from _stats import assert_mean, assert_normal_variance, binomial_interval
from conftest import REPO

DEFAULT = REPO / "config" / "default.toml"
IDEAL = REPO / "config" / "ideal.toml"
POSE = "world.start={x=0.6, y=0.25, theta_deg=0.0}"
SEED = "7"
SENSORS = ("sensors/ir", "sensors/sonar", "sensors/odometry", "sensors/gyro", "sensors/compass",
           "sensors/camera")


def load(path: Path) -> dict[str, Any]:
    with path.open("rb") as f:
        return tomllib.load(f)


def wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def first_hit(segments: np.ndarray, ox: float, oy: float, angle: float,
              max_range: float) -> tuple[float | None, float | None]:
    """Range and incidence (angle to the surface normal) of the nearest wall along a ray, or
    (None, None) beyond ``max_range``. Written here from scratch, not taken from sim/."""
    dx, dy = math.cos(angle), math.sin(angle)
    best, incidence = math.inf, None
    for x0, y0, x1, y1 in segments:
        ex, ey = x1 - x0, y1 - y0
        den = dx * ey - dy * ex
        if den == 0:
            continue
        wx, wy = x0 - ox, y0 - oy
        t = (wx * ey - wy * ex) / den
        u = (wx * dy - wy * dx) / den
        if 0 <= t < best and 0 <= u <= 1:
            best, incidence = t, math.acos(min(1.0, abs(den) / math.hypot(ex, ey)))
    return (best, incidence) if best <= max_range else (None, None)


def body_to_world(pose: dict[str, float], p: dict[str, float]) -> tuple[float, float, float]:
    c, s = math.cos(pose["theta"]), math.sin(pose["theta"])
    return (pose["x"] + c * p["x"] - s * p["y"], pose["y"] + s * p["x"] + c * p["y"],
            pose["theta"] + p["theta"])


def visible_landmarks(world: dict[str, Any], pose: dict[str, float]) -> list[dict[str, Any]]:
    """Every landmark in the camera's field of view and range, with a clear line of sight."""
    cam = world["robot"]["sensors"]["camera"]
    cx, cy, ca = body_to_world(pose, cam["pose"])
    segments = np.asarray(world["segments"], dtype=float)
    out = []
    for lm in sorted(world["landmarks"], key=lambda lm: lm["id"]):
        d = math.hypot(lm["x"] - cx, lm["y"] - cy)
        direction = math.atan2(lm["y"] - cy, lm["x"] - cx)
        if not cam["min_range_m"] <= d <= cam["max_range_m"]:
            continue
        if abs(wrap(direction - ca)) > cam["fov_rad"] / 2:
            continue
        wall, _ = first_hit(segments, cx, cy, direction, d - 1e-9)
        if wall is not None:
            continue
        out.append({"id": lm["id"], "range": d, "bearing": wrap(direction - pose["theta"])})
    return out


def table_sigma(rows: list[list[float]], r: float) -> float:
    """A [range, sigma] error table, linearly interpolated and held beyond its ends."""
    xs, ys = zip(*rows, strict=True)
    return float(np.interp(r, xs, ys))


def still_pose(messages: list[dict[str, Any]]) -> dict[str, float]:
    poses = {(m["x"], m["y"], m["theta"]) for m in messages}
    assert len(poses) == 1, f"the robot moved: {sorted(poses)[:3]}"
    x, y, theta = poses.pop()
    return {"x": x, "y": y, "theta": theta}


@pytest.fixture
def noisy_run(bridge, zenoh_watch) -> tuple[dict[str, list[dict[str, Any]]], dict[str, Any]]:
    b = bridge(clock="fast", ideal=False, config=DEFAULT, sets=[POSE], extra=["--seed", SEED])
    watch = zenoh_watch(b)
    world = watch.query("world")
    got = watch.collect({"truth/pose": 100, "sensors/gyro": 2000, "sensors/compass": 1000,
                         "sensors/ir": 400, "sensors/sonar": 200, "sensors/camera": 150,
                         "sensors/odometry": 100})
    return got, world


def test_every_model_on_differs_from_truth_as_documented(noisy_run) -> None:
    got, world = noisy_run
    cfg = load(DEFAULT)["sensors"]
    pose = still_pose(got["truth/pose"])
    assert (pose["x"], pose["y"]) == pytest.approx((0.6, 0.25))
    sensors = world["robot"]["sensors"]
    segments = np.asarray(world["segments"], dtype=float)

    # Gyro at rest (truth 0): turn-on bias b0 ~ N(0, turn_on_bias_sigma^2) plus white noise of
    # density sigma_g, per sample sigma_g / sqrt(dt) (Kalibr); the bias random walk adds
    # sigma_bg^2 T / 3 on average, well inside the interval.
    gyro = np.array([m["yaw_rate"] for m in got["sensors/gyro"]][:2000])
    assert all(m["truth"]["yaw_rate"] == 0.0 for m in got["sensors/gyro"])
    g = cfg["gyro"]
    white = g["gyroscope_noise_density"] ** 2 * sensors["gyro"]["rate_hz"]
    assert_normal_variance(gyro, white, wrong=4 * white)
    b0_bound = 4.5 * g["turn_on_bias_sigma"] + 4.5 * math.sqrt(white / gyro.size)
    assert abs(gyro.mean()) <= b0_bound

    # Compass at rest: B_m = S B + b_hard + n; the offset from S B is the hard iron.
    c = cfg["compass"]
    soft = np.asarray(c["soft_iron"], dtype=float)
    measured = np.array([[m["mx"], m["my"], m["mz"]] for m in got["sensors/compass"]])
    truth = np.array([[m["truth"][k] for k in ("mx", "my", "mz")]
                      for m in got["sensors/compass"]])
    residual = measured - truth @ soft.T
    for axis in range(3):
        assert_mean(residual[:, axis], c["hard_iron_uT"][axis], c["noise_sigma_uT"], wrong=0.0)
        assert_normal_variance(residual[:, axis], c["noise_sigma_uT"] ** 2)

    # IR: truth {counts, ranges, incidence}; ranges and incidence are the axis rays' geometry;
    # measured counts are scaled by the ambient-light loss, with count noise (docs/models.md).
    ir_cfg, ir = cfg["ir"], sensors["ir"]
    expected = [
        first_hit(segments, *body_to_world(pose, p), ir["max_range_m"]) for p in ir["poses"]
    ]
    for m in got["sensors/ir"]:
        assert m["truth"]["ranges"] == pytest.approx([r for r, _ in expected], abs=1e-9)
        assert m["truth"]["incidence"] == pytest.approx([a for _, a in expected], abs=1e-9)
    assert sum(r is not None for r, _ in expected) >= 3  # the wall is seen
    counts = np.array([m["counts"] for m in got["sensors/ir"]], dtype=float)
    true_counts = np.array([m["truth"]["counts"] for m in got["sensors/ir"]], dtype=float)
    gain = 1 - ir_cfg["ambient_saturation"] * ir_cfg["ambient_counts"] / ir_cfg["max_counts"]
    seen = true_counts[0] > 20
    assert seen.sum() >= 2
    for i in np.flatnonzero(seen):
        diff = counts[:, i] - gain * true_counts[:, i]
        half = 4.5 * diff.std() / math.sqrt(diff.size) + 0.5  # + rounding
        assert abs(diff.mean()) <= half, (i, diff.mean(), half)
        assert diff.std() >= ir_cfg["count_noise_sigma"] * 0.8
    # Nothing in range: truth 0, and counts round(max(0, sigma n)): P(0) = Phi(0.5 / sigma).
    dark = counts[:, true_counts[0] == 0].ravel()
    p0 = float(0.5 * (1 + math.erf(0.5 / ir_cfg["count_noise_sigma"] / math.sqrt(2))))
    lo, hi = binomial_interval(dark.size, p0)
    assert lo <= int((dark == 0).sum()) <= hi

    # Sonar: where the nearest surface is within the critical angle, it gives the direct echo:
    # measured = truth + sigma(truth) z (seeds/004 table), except glitches U(min, max).
    s_cfg, sonar = cfg["sonar"], sensors["sonar"]
    critical = math.radians(s_cfg["critical_angle_deg"])
    z = []
    for m in got["sensors/sonar"]:
        for meas, r, inc in zip(m["ranges"], m["truth"]["ranges"], m["truth"]["incidence"],
                                strict=True):
            if r is None or inc is None or inc > critical or r < sonar["min_range_m"] + 0.05:
                continue
            assert meas is not None
            z.append((meas - r) / table_sigma(s_cfg["distance_error"], r))
    z_arr = np.array(z)
    assert z_arr.size >= 150
    outliers = np.abs(z_arr) > 6
    _, glitch_hi = binomial_interval(z_arr.size, s_cfg["glitch_probability"])
    assert outliers.sum() <= glitch_hi
    assert_normal_variance(z_arr[~outliers], 1.0, mean=0.0)

    # Camera: truth is every landmark in view, with its true id, range and bearing; the
    # measured bearing carries N(0, bearing_sigma) (eq. 14), observations are sometimes missed.
    want = visible_landmarks(world, pose)
    assert want, "landmark 3 should be in view"
    errors = []
    observed = 0
    for m in got["sensors/camera"]:
        assert [o["id"] for o in m["truth"]["observations"]] == [o["id"] for o in want]
        for o, w in zip(m["truth"]["observations"], want, strict=True):
            assert (o["range"], o["bearing"]) == pytest.approx((w["range"], w["bearing"]),
                                                               abs=1e-9)
        observed += len(m["observations"])
        truth_by_id = {o["id"]: o for o in m["truth"]["observations"]}
        errors += [wrap(o["bearing"] - truth_by_id[o["id"]]["bearing"])
                   for o in m["observations"] if o["id"] in truth_by_id]
    assert observed < len(got["sensors/camera"]) * len(want)  # some misses
    err = np.array(errors)
    err = err[np.abs(err) < math.radians(10 * cfg["camera"]["bearing_sigma_deg"])]  # wrong ids
    assert err.size >= 30
    assert_normal_variance(err, math.radians(cfg["camera"]["bearing_sigma_deg"]) ** 2, mean=0.0)


def test_every_model_off_measures_exactly_the_truth(bridge, zenoh_watch) -> None:
    b = bridge(clock="fast", ideal=False, config=IDEAL, sets=[POSE], extra=["--seed", SEED])
    watch = zenoh_watch(b)
    world = watch.query("world")
    with serial.Serial(b.endpoints["serial"]["kteam"], 115200, timeout=5) as kt:
        kt.write(b"D,8,-8\r")  # turn on the spot: the gyro and the compass change
        assert kt.read_until(b"\r\n") == b"d\r\n"
        time.sleep(0.2)
        got = watch.collect({key: n for key, n in zip(SENSORS, (100, 30, 300, 300, 200, 30),
                                                      strict=True)})
    min_range = world["robot"]["sensors"]["sonar"]["min_range_m"]
    assert any(m["yaw_rate"] != 0 for m in got["sensors/gyro"])
    for m in got["sensors/ir"]:
        assert m["counts"] == m["truth"]["counts"]
    for m in got["sensors/sonar"]:
        for meas, r in zip(m["ranges"], m["truth"]["ranges"], strict=True):
            # The Koala reads 0 below its minimum range; the truth keeps the distance.
            assert meas == (0.0 if r is not None and r < min_range else r), m
    for m in got["sensors/odometry"]:
        assert (m["left_ticks"], m["right_ticks"]) == (m["truth"]["left_ticks"],
                                                       m["truth"]["right_ticks"])
    for m in got["sensors/gyro"]:
        assert m["yaw_rate"] == m["truth"]["yaw_rate"]
    for m in got["sensors/compass"]:
        assert (m["mx"], m["my"], m["mz"]) == (m["truth"]["mx"], m["truth"]["my"],
                                               m["truth"]["mz"])
    for m in got["sensors/camera"]:
        assert m["observations"] == m["truth"]["observations"]
    assert any(m["observations"] for m in got["sensors/camera"])
