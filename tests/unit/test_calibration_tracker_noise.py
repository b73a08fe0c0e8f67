"""A gyro against a motion tracker whose heading has a little white noise (0.3 mrad at 50 Hz):
a small share of the reference's variance (the robot turns fast), but most of the rate
residual's, as differenced noise (0.3 mrad * sqrt(2) * 50 Hz = 0.021 rad/s against the gyro's
0.0013). An independent study's generator found two faults there, each fixed here:

* a clean gyro got a ``time_offset`` of 9-15 ms, "better by 16-39 %" in rate space (4 of 28
  clean cases, the heading 8 times worse): a shift of a fraction of a sample reads the
  reference between its samples, where interpolation smooths its noise (half a sample over, a
  quarter of its variance is left), not a latency;
* a real latency was fitted a few milliseconds short with a standard error 30-150 times
  smaller than the error, pulled towards the shifts that smooth most.

Where the reference's noise is most of the rate residual (``pipeline.RESIDUAL_NOISE_SHARE``,
the residual also measured after the best latency and gain a line through the reference
finds), the gyro is compared in heading space, where noise integrates out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream, gyro_bundle
from koala_bridge.calibration import pipeline
from koala_bridge.calibration.synthetic import DECLARED

DURATION_S = 300.0
RATE_HZ = 50.0
HEADING_NOISE = 3e-4
GYRO_NOISE = 0.0013


def _omega(t: np.ndarray) -> np.ndarray:
    """Turns both ways, up to ~1.6 rad/s, that do not repeat within the recording."""
    return 1.0 * np.sin(2 * np.pi * t / 13.0) + 0.6 * np.sin(2 * np.pi * t / 5.3 + 1.0)


def _bundle(out: Path, seed: int, late_s: float = 0.0) -> Path:
    """The tracker's heading and the gyro, both at ``RATE_HZ`` on the same stamps; the gyro
    reads the rate ``late_s`` seconds late."""
    rng = np.random.default_rng(seed)
    fine = np.arange(0.0, DURATION_S + 1.0, 0.001)
    theta_fine = np.r_[0.0, np.cumsum(0.5 * (_omega(fine[1:]) + _omega(fine[:-1])) * 0.001)]
    t = np.arange(0.0, DURATION_S, 1.0 / RATE_HZ)
    theta = np.interp(t, fine, theta_fine) + rng.normal(0.0, HEADING_NOISE, t.size)
    rate = _omega(t - late_s) + rng.normal(0.0, GYRO_NOISE, t.size)
    return gyro_bundle(out, t, theta, rate)


@pytest.mark.parametrize("seed", range(3))
def test_a_clean_gyro_against_a_noisy_tracker_gets_no_latency(tmp_path: Path, seed: int) -> None:
    res, _ = calibrate_stream(_bundle(tmp_path / "b", seed), "gyro", DECLARED)
    assert res is not None
    assert res.problem.integrate_window_s is not None  # heading space
    assert any("% of the rate residual's" in n for n in res.problem.notes)
    assert [i.name for i in res.effects] == []


def test_in_rate_space_the_tracker_s_noise_reads_as_a_latency(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # what the switch is for (the criterion off): rate with rate, a sub-sample shift smooths
    monkeypatch.setattr(pipeline, "RESIDUAL_NOISE_SHARE", np.inf)
    res, _ = calibrate_stream(_bundle(tmp_path / "b", 0), "gyro", DECLARED)
    assert res is not None and res.problem.integrate_window_s is None
    assert "time_offset" in [i.name for i in res.effects]
    ((p, _),) = [(p, s) for (p, s), i in zip(res.effect_params(), res.effects, strict=True)
                 if i.name == "time_offset"]
    assert 0 < abs(p["tau_s"]) < 1.0 / RATE_HZ  # a fraction of a sample


@pytest.mark.parametrize(("late_s", "seed"), [(0.148, 1), (0.254, 1), (0.14, 0), (0.3, 0)])
def test_a_real_latency_is_fitted_where_it_is(tmp_path: Path, late_s: float, seed: int) -> None:
    """Between the tracker's samples (0.148, 0.254 s: rate space fitted them 1-2 ms off, pulled
    towards the shifts that smooth most) and at a whole number of them (0.14, 0.3 s: a
    reviewer's sweep, where the reference read at the latency is not smoothed, the noise
    estimate came out 0.45 of the residual, and rate space fitted 0.134 s for 0.14, 42 SE
    off): in heading space, within 4 SE."""
    res, _ = calibrate_stream(_bundle(tmp_path / "b", seed, late_s), "gyro", DECLARED)
    assert res is not None and res.problem.integrate_window_s is not None
    assert [i.name for i in res.effects] == ["time_offset"]
    ((p, se),) = res.effect_params()
    assert abs(p["tau_s"] - late_s) < 4 * se["tau_s"], (p, se)


@pytest.mark.parametrize("gain", [1.6, 2.0])
def test_a_mis_scaled_gyro_against_the_tracker_gets_no_latency(
    tmp_path: Path, gain: float
) -> None:
    """The reference's noise is compared in the readings' unit: a gyro of gain 2 stayed in
    rate space by the gain squared and got a -6 ms latency beside its scale."""
    path = _bundle(tmp_path / "b", 2)
    gyro = path / "gyro.csv"
    rows = np.loadtxt(gyro, delimiter=",", skiprows=1)
    rows[:, 1] *= gain
    np.savetxt(gyro, rows, delimiter=",", header="t,yaw_rate", comments="", fmt="%.10g")
    res, _ = calibrate_stream(path, "gyro", DECLARED)
    assert res is not None
    assert [i.name for i in res.effects] == ["scale"]


def _short_bundle(out: Path, seed: int, late_s: float) -> Path:
    """15 s of a gyro at 50 Hz against a tracker's heading at 100 Hz with 2 mrad of noise (a
    navX against motion capture, cut where the tracker's tilt stayed small): 6 s held out."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 15.0, 0.01)
    ph = rng.uniform(0.0, 2 * np.pi, 3)
    w = (0.8 * np.sin(2 * np.pi * t / 3.1 + ph[0]) + 0.5 * np.sin(2 * np.pi * t / 1.3 + ph[1])
         + 0.3 * np.sin(2 * np.pi * t / 0.7 + ph[2]))
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    t_gyro = t[::2]
    rate = np.interp(t_gyro - late_s, t, w) + rng.normal(0.0, 0.01, t_gyro.size)
    return gyro_bundle(out, t, theta + rng.normal(0.0, 2e-3, t.size), rate, gyro_t=t_gyro)


@pytest.mark.parametrize("seed", range(3))
def test_a_latency_on_a_short_recording_is_found(tmp_path: Path, seed: int) -> None:
    """6 s held out is less than one 10 s heading window: about 1.3 independent units, and no
    effect could pass (a real navX's 37 ms, a hand fit's held-out error 76 % lower, was
    'not significant'). Against a tracker the windows are then a quarter of the held-out
    part; the latency is found, and a clean gyro gets none."""
    res, _ = calibrate_stream(_short_bundle(tmp_path / "late", seed, 0.04), "gyro")
    assert res is not None
    assert res.problem.integrate_window_s == pytest.approx(1.5, abs=0.01)
    assert [i.name for i in res.effects] == ["time_offset"]
    ((p, se),) = res._params_and_se()
    assert se is not None and abs(float(p[0]) - 0.04) < 4 * float(se[0])
    clean, _ = calibrate_stream(_short_bundle(tmp_path / "clean", seed, 0.0), "gyro")
    assert clean is not None and clean.effects == []
