"""3-D / tilt awareness: a gyro z bias found on the level segments of an IMU moved in 3-D.

Synthetic IMU (bridge/calibration/synthetic_imu.py): the body turns while, in episodes, it rolls
or pitches up to 90 deg; tilted, the z gyro reads psi' cos(pitch) cos(roll) plus the tilt rates
mixed in. On the whole stream that shows as a coupling to rate_x/rate_y and hides the bias; on
the level segments (gravity within 3 deg of z) the reading is psi' + b + noise.

Bound: on the level segments the residual is b + white noise of the generator's sigma, so the
least-squares bias on the fit part's n samples has standard error sigma / sqrt(n); the found bias
must lie within 4 of them (two-sided false alarm 6e-5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import Bundle, load_bundle
from koala_bridge.calibration.config_update import found_keys
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.problem import SkippedStream
from koala_bridge.calibration.streams.level import level_mask, tilt_from_accelerometer
from koala_bridge.calibration.synthetic_imu import TiltCase, make_tilt_bundle, tilt_angles

Z = 4.0
IDEAL = {"sensors": {"gyro": {"ideal": True}}}


@pytest.mark.parametrize("accelerometer", [True, False])
def test_z_bias_found_on_level_segments(tmp_path: Path, accelerometer: bool) -> None:
    case = TiltCase()
    bundle = load_bundle(make_tilt_bundle(tmp_path / "imu", 5, case, accelerometer))
    skipped: list[SkippedStream] = []
    model = declared_model(IDEAL, bundle.meta)
    results = {r.problem.name: r for r in calibrate(bundle, model, skipped=skipped)}
    assert set(results) == {"gyro", "gyro:level"} and skipped == []
    level = results["gyro:level"]
    assert [i.name for i in level.effects] == ["bias"]
    n_fit = int(level.problem.split.mask(level.problem.t, "fit").sum())
    se = case.noise / np.sqrt(n_fit)
    assert se < 0.01 * case.bias  # a bound a wrong bias fails
    ((params, _),) = level.effect_params()
    assert abs(params["bias"] - case.bias) < Z * se
    # the written gyro bias is the level segments' (the stream after the whole gyro)
    assert abs(found_keys(list(results.values()))["sensors.gyro.bias_rad_s"] - case.bias) < Z * se
    # the whole stream's tilt error shows as a coupling to the other axes' rates
    whole = results["gyro"]
    assert any(i.name.startswith("covariate:rate_") for i in whole.effects)
    assert any("gyro:level" in n for n in whole.problem.notes)
    # held out on the level segments: the bias was the error, the noise is left
    n = level.problem.residuals([], np.empty(0), "score").size
    assert level.after < case.noise * (1 + Z / np.sqrt(2 * n)) < level.before


def test_level_mask_follows_the_tilt(tmp_path: Path) -> None:
    """Level from gravity: every sample the generator tilted by more than 3 deg plus the
    accelerometer noise's worth is not level; the level ones were tilted by at most that."""
    case = TiltCase()
    bundle = load_bundle(make_tilt_bundle(tmp_path / "imu", 6, case))
    _, _, th, ph = tilt_angles(case)
    true_tilt = np.degrees(np.arccos(np.cos(th) * np.cos(ph)))
    found = level_mask(bundle.tables["gyro"])
    assert found is not None and "accelerometer" in found[1]
    mask = found[0]
    # the accelerometer's noise (0.05 m/s^2 per axis) moves the tilt by < 4 sigma / g rad
    slack = np.degrees(Z * case.acc_noise / 9.80665)
    assert true_tilt[mask].max() < 3.0 + slack
    assert not mask[true_tilt > 3.0 + slack].any()
    assert 0.4 < mask.mean() < 0.9  # level half of the time, tilted the other half


def test_tilt_from_accelerometer() -> None:
    g = 9.81
    acc = np.array([[0, 0, g], [g, 0, 0], [0, -g, 0], [0, 0, -g], [0, g / 2, g * np.sqrt(3) / 2]])
    assert np.degrees(tilt_from_accelerometer(acc)) == pytest.approx([0, 90, 90, 180, 30])


def test_no_level_stream_without_tilts(tmp_path: Path) -> None:
    """A gyro level all the time is its own level stream: nothing is added."""
    bundle = load_bundle(make_tilt_bundle(tmp_path / "imu", 7, TiltCase(amplitudes_deg=())))
    names = [r.problem.name for r in calibrate(bundle, declared_model(IDEAL, bundle.meta))]
    assert names == ["gyro"]


@pytest.mark.parametrize("seed", [0, 1])
def test_level_segments_against_a_noisy_heading_are_compared_in_heading_space(
    tmp_path: Path, seed: int
) -> None:
    """A real IMU moved by hand under motion capture (a new user's trial): its level segments'
    -0.011 rad/s z bias, plain in both still periods, was judged rate with rate against a
    heading whose differenced rate was 90 % noise, and not named (0.5 % better). The level
    stream now goes to heading space as the whole stream does, its windows starting again after
    each tilted gap and a quarter of the held-out part long at most."""
    case = TiltCase(bias=-0.011, noise=0.003, duration_s=60.0, rate_hz=100.0, period_s=20.0,
                    episode_s=10.0, amplitudes_deg=(45.0, 60.0, 30.0))
    path = make_tilt_bundle(tmp_path / "imu", seed, case)
    truth = path / "truth_pose.csv"
    rows = np.loadtxt(truth, delimiter=",", skiprows=1)
    rows[:, 3] += np.random.default_rng(100 + seed).normal(0.0, 0.005, rows.shape[0])
    np.savetxt(truth, rows, delimiter=",", header="t,x,y,theta", comments="", fmt="%.9g")
    bundle = load_bundle(path)
    results = {r.problem.name: r for r in calibrate(bundle, declared_model(IDEAL, bundle.meta))}
    level = results["gyro:level"]
    # the whole stream says how much of it is tilted, where its z gyro reads no heading rate
    (tilted,) = (n for n in results["gyro"].problem.notes if "tilted off its level" in n)
    share = 1 - level.problem.t.size / results["gyro"].problem.t.size
    assert f"about {100 * share:.0f} % of the samples" in tilted
    assert level.problem.integrate_window_s is not None  # heading space
    assert level.problem.window_gap_s is not None
    assert [i.name for i in level.effects] == ["bias"]
    ((p, se),) = level.effect_params()
    assert abs(p["bias"] - case.bias) < Z * se["bias"], (p, se)


def test_a_level_sensor_on_an_accelerating_robot_is_said_to_be_possibly_accelerating(
    tmp_path: Path,
) -> None:
    """An accelerometer reads a horizontal acceleration as a tilt (1 m/s^2 is 5.8 deg), and
    |a| cannot see it (it grows by 0.5 %). A navX on a driving robot read "tilted on 76 %"
    where motion capture had it level: where most of the accelerometer's tilt changes come
    with no rotation in the x/y rates, the note says so. A sensor that does tilt (rotating as
    its tilt changes) gets no such clause."""
    d = make_tilt_bundle(tmp_path / "imu", 7, TiltCase(amplitudes_deg=()))
    path = d / "gyro.csv"
    header = path.read_text().splitlines()[0]
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    cols = header.split(",")
    t = rows[:, 0]
    # the robot starts and brakes: 1 m/s^2 forward in every other 3 s of each 12 s
    rows[:, cols.index("acc_x")] += np.where((t % 12.0) < 3.0, 1.0, 0.0)
    np.savetxt(path, rows, delimiter=",", header=header, comments="", fmt="%.10g")
    bundle = load_bundle(d)
    results = {r.problem.name: r for r in calibrate(bundle, declared_model(IDEAL, bundle.meta))}
    assert set(results) == {"gyro", "gyro:level"}  # the accelerometer's "tilts" split it
    (note,) = [n for n in results["gyro"].problem.notes if "tilted off its level" in n]
    assert "of the accelerometer's tilt changes come with no rotation" in note
    tilting = load_bundle(make_tilt_bundle(tmp_path / "tilting", 5, TiltCase()))
    results = {r.problem.name: r for r in calibrate(tilting, declared_model(IDEAL, tilting.meta))}
    (note,) = [n for n in results["gyro"].problem.notes if "tilted off its level" in n]
    assert "no rotation" not in note
    # a robot driving up a 12 deg ramp, held still on it: rotating as its tilt changes
    ramp = _ramp_bundle(tmp_path / "ramp")
    results = {r.problem.name: r for r in calibrate(ramp, declared_model(IDEAL, ramp.meta))}
    (note,) = [n for n in results["gyro"].problem.notes if "tilted off its level" in n]
    assert "no rotation" not in note


def _ramp_bundle(out: Path) -> Bundle:
    """An IMU on a robot that drives up a 12 deg ramp and down again every 40 s, held 16 s on
    it without turning, and turns on the flat (a reviewer's case: its x/y rates are ~0 on the
    ramp, where the tilt is real)."""
    g = 9.80665
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 240.0, 0.02)
    on = np.zeros_like(t)
    for k in range(6):
        t0 = 40.0 * k + 10.0
        on += np.clip((t - t0) / 2, 0, 1) * np.clip((t0 + 20 - t) / 2, 0, 1)
    pitch = np.deg2rad(12.0) * on
    yaw_rate = np.where(on > 0, 0.0, 0.5 + 0.3 * np.sin(t / 2))
    yaw = np.r_[0.0, np.cumsum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * 0.02)]
    d_yaw, d_pitch = np.gradient(yaw, t), np.gradient(pitch, t)
    # body rates of yaw then pitch (no roll)
    p, q, r = -d_yaw * np.sin(pitch), d_pitch, d_yaw * np.cos(pitch)
    f = g * np.column_stack([-np.sin(pitch), 0 * t, np.cos(pitch)])
    f += rng.normal(0.0, 0.05, f.shape)
    out.mkdir(parents=True)
    noise = [rng.normal(0.0, 0.005, t.size) for _ in range(3)]
    np.savetxt(out / "gyro.csv",
               np.column_stack([t, r + 0.02 + noise[0], p + noise[1], q + noise[2], *f.T]),
               delimiter=",", header="t,yaw_rate,rate_x,rate_y,acc_x,acc_y,acc_z",
               comments="", fmt="%.10g")
    np.savetxt(out / "truth_pose.csv", np.column_stack([t, 0 * t, 0 * t, yaw]), delimiter=",",
               header="t,x,y,theta", comments="", fmt="%.10g")
    (out / "meta.json").write_text("{}", encoding="utf-8")
    return load_bundle(out)
