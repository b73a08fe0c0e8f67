"""A gyro against a dense heading that is mostly its own noise once differenced (a new user's
MPU-6050 turned by hand against its accelerometer's roll angle: 81 % noise in rate space).

Rate space said nothing there: a 0.057 rad/s bias went unnamed. Such a stream is compared in
heading space (streams.to_heading_space), where white noise shrinks with integration; a time
offset stays judged against the rate's noise (a shift smooths it), a scale against the
heading's. A scale through zero on readings that do not run against the reference is not called
a sign convention.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from _bundles import gyro_bundle
from koala_bridge.calibration import pipeline
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.effects import get_effect
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.problem import Split
from koala_bridge.calibration.synthetic import DECLARED

BIAS = 0.05
#: the reference heading's white noise (rad): an accelerometer's roll angle, 100 Hz
SIGMA = 0.02


def _bundle(out: Path, seed: int) -> Path:
    """100 s at 100 Hz: still, a 92 deg turn from 14 to 23 s, still again; the reference heading
    with white noise ``SIGMA``; the gyro with ``BIAS`` and 0.002 rad/s of noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    w = np.where((t > 14) & (t < 23), 1.6 / 9 * (1 - np.cos(2 * np.pi * (t - 14) / 9)), 0.0)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    return gyro_bundle(out, t, theta + rng.normal(0, SIGMA, t.size),
                       w + BIAS + rng.normal(0, 0.002, t.size))


def _gyro(path: Path):  # noqa: ANN202 - a StreamResult
    bundle = load_bundle(path)
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    return res


def test_a_noisy_dense_reference_is_compared_in_heading_space(tmp_path: Path) -> None:
    res = _gyro(_bundle(tmp_path / "b", 0))
    assert res.problem.metric == "heading_error_10s_running_rms"
    assert any(n.startswith("compared in heading space") for n in res.problem.notes)
    # the time shift that would smooth the reference's noise is not tried
    assert any(n.startswith("time_offset not tried") for n in res.problem.notes)
    # a gain is judged against the heading's noise share, small beside a 92 deg turn: tried
    assert not any(n.startswith("scale not tried") for n in res.problem.notes)
    assert "scale" in [t.name for t in res.selection.rounds[0]]
    # the noise no longer reaches a residual's Allan analysis
    assert res.noise is None
    assert [i.name for i in res.effects] == ["bias"]
    ((p, se),) = res._params_and_se()
    assert se is not None and abs(float(p[0]) - BIAS) < 4 * float(se[0])


def test_rate_space_on_the_same_data_misses_the_bias(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # what the switch is for: rates compared with a reference that is mostly noise
    monkeypatch.setattr(pipeline, "MAX_REFERENCE_NOISE_SHARE", 1.0)
    monkeypatch.setattr(pipeline, "HEADING_SPACE_SHARE", 1.0)
    monkeypatch.setattr(pipeline, "RESIDUAL_NOISE_SHARE", np.inf)
    res = _gyro(_bundle(tmp_path / "b", 0))
    assert res.problem.metric == "rms_rate_error"
    assert "bias" not in [i.name for i in res.effects]


def _still_filtered(out: Path, seed: int, tau: float, bias: float) -> Path:
    """A still gyro (``bias``, 0.002 rad/s of noise) against a heading whose 0.02 rad of noise is
    low-passed with time constant ``tau`` (AR(1)): an accelerometer's angle through a filter."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    a = np.exp(-0.01 / tau)
    z = rng.normal(0.0, 0.02 * np.sqrt(1 - a * a), t.size)
    e = np.zeros(t.size)
    for i in range(1, t.size):
        e[i] = a * e[i - 1] + z[i]
    return gyro_bundle(out, t, 0.3 + e, bias + rng.normal(0.0, 0.002, t.size))


@pytest.mark.parametrize("tau", [0.05, 1.0])
def test_filtered_heading_noise_is_no_motion_for_a_scale(tmp_path: Path, tau: float) -> None:
    # Its sixth differences see none of a smoothed noise: measured so, its windows' changes
    # looked like motion, and a still gyro got a scale of -1 (gain 0) on about half the seeds.
    # The readings follow none of it: the share is ~1 and no scale is tried. The bias (0.1 rad
    # a window against 0.02 of noise) is found where the noise is white at the windows' scale
    # (tau 0.05 s); at tau = 1 s the 4 held-out windows hold fewer units, and it may not be.
    for seed in range(3):
        res = _gyro(_still_filtered(tmp_path / f"b{seed}", 9000 + seed, tau, 0.01))
        assert res.problem.metric == "heading_error_10s_running_rms"
        assert res.problem.heading_share is not None and res.problem.heading_share > 0.9
        assert any(n.startswith("scale not tried") for n in res.problem.notes)
        assert {i.name for i in res.effects} <= {"bias"}
        if tau < 0.1:
            assert [i.name for i in res.effects] == ["bias"]


def test_the_heading_share_of_a_turning_gyro_is_its_white_noise(tmp_path: Path) -> None:
    # the same 0.02 rad, white, beside a turn back and forth of +-0.9 rad: the share is the
    # noise's variance over the path's, about 2 sigma^2 / mean square of the path
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    w = 0.8 * np.sin(2 * np.pi * t / 7)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    res = _gyro(gyro_bundle(tmp_path / "b", t, theta + rng.normal(0.0, 0.02, t.size),
                            w + rng.normal(0.0, 0.002, t.size)))
    assert res.problem.metric == "heading_error_10s_running_rms"
    path = theta - theta[0]  # sin path, mean square about 0.9^2 (1/2 + 1): window anchors vary
    share = res.problem.heading_share
    assert share is not None and share < 5 * 2 * 0.02**2 / np.mean((path - path.mean()) ** 2)
    assert res.effects == []


@pytest.mark.parametrize(("sign", "says"), [(1.0, "do not run against the reference"),
                                            (-1.0, "sign convention differs")])
def test_a_scale_through_zero_is_a_sign_only_when_the_readings_run_against(
    sign: float, says: str
) -> None:
    t = np.arange(0.0, 10.0, 0.01)
    u = np.sin(t)
    problem = SimpleNamespace(y=sign * u + 0.3, u=u, t=t, split=Split.of(t), quantity="yaw rate")
    effect = get_effect("scale")
    inst = EffectInstance("scale", effect, ("scale_error",), (0.0,))
    why = effect.implausible_reason(inst, np.array([-1.5]), problem)
    assert why is not None and says in why


def test_a_held_out_part_without_motion_is_said(tmp_path: Path) -> None:
    # the turn is in the first 60 % of the time: a gain is scored on the rest only through
    # the bias; a recording that turns in both parts gets no such note
    res = _gyro(_bundle(tmp_path / "b", 0))
    (note,) = (n for n in res.problem.notes if n.startswith("the held-out part holds little"))
    assert "record turns in the last 40 %" in note
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    w = 0.5 * np.sin(2 * np.pi * t / 13)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    turning = _gyro(gyro_bundle(tmp_path / "c", t, theta, w + BIAS))
    assert not any(n.startswith("the held-out part holds little")
                   for n in turning.problem.notes)


def test_a_fit_part_without_motion_is_said(tmp_path: Path) -> None:
    # the mirror: still for the first 60 %, a turn in the last 40 %
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    w = np.where((t > 70) & (t < 79), 1.6 / 9 * (1 - np.cos(2 * np.pi * (t - 70) / 9)), 0.0)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    res = _gyro(gyro_bundle(tmp_path / "b", t, theta, w + BIAS))
    (note,) = (n for n in res.problem.notes if n.startswith("the fit part holds little motion"))
    assert "record turns in the first 60 %" in note
    assert not any(n.startswith("the held-out part holds little") for n in res.problem.notes)


def test_a_sign_flipped_gyro_in_heading_space_is_named_a_sign(tmp_path: Path) -> None:
    """The turning gyro above with its sign flipped: unsigned, its heading share read 1 ("the
    readings do not follow it"), scale was not tried, and the report blamed the reference's
    noise (a car's gyro, flipped by a new user, turning 3.2 rad on the fit part). Signed, the
    share is the unflipped one's; the scale is tried, fitted through zero, and named a sign."""
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 100.0 + 0.005, 0.01)
    w = 0.8 * np.sin(2 * np.pi * t / 7)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    res = _gyro(gyro_bundle(tmp_path / "b", t, theta + rng.normal(0.0, 0.02, t.size),
                            -w + rng.normal(0.0, 0.002, t.size)))
    assert res.problem.metric == "heading_error_10s_running_rms"
    assert res.problem.heading_share is not None and res.problem.heading_share < 0.1
    assert not any(n.startswith("scale not tried") for n in res.problem.notes)
    assert any("the readings run against the reference" in n for n in res.problem.notes)
    assert res.effects == []
