"""A compass held against a heading reference uses only the readings taken level.

A magnetometer's x and y give the heading only while its z axis is vertical: tilted, they mix
in the vertical field (here -40 uT against a horizontal 20 uT). The BROAD IMU, turned by hand
through 3-D, got a hard iron of (-9.6, 6.0) uT "better by 21 %" from its tilted readings; the
sensor had none. With an accelerometer in gyro.csv the compass stream keeps the level readings
(``streams._compass_level``, the level test of ``streams.level``) and says so; a clean sensor
then gets no effect, and its heading error is its noise's.

Bound: per-axis noise ``sigma`` on a horizontal field ``B`` gives a heading error of about
``sigma / B`` rad; the held-out RMS must be within 1.5 of that (1 500 level readings: the RMS
of n Gaussians is within 1.5 sigma with certainty for practical purposes).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from _bundles import calibrate_stream
from koala_bridge.calibration.problem import SkippedStream

RATE_HZ = 20.0
FIELD = np.array([20.0, 0.0, -40.0])  # uT, world frame (x north, z up): dipping down
SIGMA_UT = 0.3
ROLL = np.deg2rad(30.0)


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _bundle(tmp_path: Path, tilted_every: int | None, mount_deg: float = 0.0) -> Path:
    """Turning at 0.5 rad/s for 150 s; every other ``tilted_every`` seconds rolled 30 deg;
    the sensor mounted rolled ``mount_deg`` throughout."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 150.0, 1 / RATE_HZ)
    theta = 0.5 * t
    tilted = (t // tilted_every) % 2 == 1 if tilted_every else np.zeros(t.size, dtype=bool)
    mag, acc = [], []
    for th, tl in zip(theta, tilted, strict=True):
        r = _rz(th) @ _rx((ROLL if tl else 0.0) + np.deg2rad(mount_deg))  # body -> world
        mag.append(r.T @ FIELD)
        acc.append(r.T @ np.array([0.0, 0.0, 9.81]))
    m = np.array(mag) + rng.normal(0.0, SIGMA_UT, (t.size, 3))
    a = np.array(acc) + rng.normal(0.0, 0.02, (t.size, 3))
    d = tmp_path / "imu"
    d.mkdir()
    rows = "".join(f"{k:.3f},{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in zip(t, m, strict=True))
    (d / "compass.csv").write_text("t,mx,my,mz\n" + rows)
    (d / "gyro.csv").write_text("t,yaw_rate,acc_x,acc_y,acc_z\n" + "".join(
        f"{k:.3f},0.5,{x:.4f},{y:.4f},{z:.4f}\n" for k, (x, y, z) in zip(t, a, strict=True)))
    (d / "truth_pose.csv").write_text("t,x,y,theta\n" + "".join(
        f"{k:.3f},0,0,{th:.6f}\n" for k, th in zip(t, theta, strict=True)))
    (d / "meta.json").write_text(json.dumps({"units": {"compass.mx": "uT"}}))
    return d


def _compass(d: Path) -> tuple[object, list[SkippedStream]]:
    return calibrate_stream(d, "compass")


def test_a_tilted_compass_is_held_to_its_level_readings(tmp_path: Path) -> None:
    res, _ = _compass(_bundle(tmp_path, tilted_every=10))
    assert res is not None
    assert [i.name for i in res.effects] == []  # a clean sensor: nothing to add
    assert res.after < 1.5 * SIGMA_UT / np.hypot(FIELD[0], FIELD[1])
    note = " ".join(res.problem.notes)
    assert "level readings only" in note
    assert res.problem.t.size < 0.6 * 150 * RATE_HZ  # about half the readings were tilted


def test_a_compass_tilted_throughout_is_skipped_with_the_reason(tmp_path: Path) -> None:
    res, skipped = _compass(_bundle(tmp_path, tilted_every=1))
    # tilted every other second: no level stretch of 1 s survives the accelerometer's test
    assert res is None
    (s,) = [s for s in skipped if s.stream == "compass"]
    assert "the sensor tilts" in s.missing
    assert "level" in s.fix


def test_a_level_compass_keeps_every_reading(tmp_path: Path) -> None:
    res, _ = _compass(_bundle(tmp_path, tilted_every=None))
    assert res is not None
    assert res.problem.t.size == int(150 * RATE_HZ)
    assert not any("level readings only" in n for n in res.problem.notes)


def test_a_constant_mounting_tilt_is_not_tilting(tmp_path: Path) -> None:
    """Mounted 4 deg off (or an accelerometer's zero-g offset): every reading is at the same
    attitude, nothing is set aside, and the constant the vertical field adds to x/y is what a
    hard iron models (40 uT sin 4 deg = 2.8 uT on y). It was once skipped as 'tilted'."""
    res, skipped = _compass(_bundle(tmp_path, tilted_every=None, mount_deg=4.0))
    assert res is not None and not [s for s in skipped if s.stream == "compass"]
    assert res.problem.t.size == int(150 * RATE_HZ)
    assert not any("level readings only" in n for n in res.problem.notes)
    assert "hard_iron" in [i.name for i in res.effects]
