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
from koala_bridge.calibration.streams import heading_noise_share, heading_noise_sigma
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
    assert res.problem.metric == "heading_error_10s_window_rms"
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
    res = _gyro(_bundle(tmp_path / "b", 0))
    assert res.problem.metric == "rms_rate_error"
    assert "bias" not in [i.name for i in res.effects]


def test_heading_noise_sigma_and_share() -> None:
    # The robust spread of 6th differences over sqrt(924): its standard error is a few per
    # cent on 10 000 samples (MAD: 1.67 sigma / sqrt(n_eff), the differences correlated over 7
    # samples: n_eff ~ 1400, 4.5 %); 20 % is 4 of them.
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 100.0, 0.01)
    smooth = 0.8 * np.sin(2 * np.pi * t / 17)
    assert heading_noise_sigma(smooth + rng.normal(0, 0.01, t.size)) == pytest.approx(0.01,
                                                                                      rel=0.2)
    assert heading_noise_sigma(smooth) < 1e-6
    # in heading space the same noise is small beside a turn's change per window: a fraction
    # 2 sigma^2 / mean(change^2) of it
    share = heading_noise_share(t, smooth + rng.normal(0, 0.01, t.size), 0.0, 99.0)
    changes = np.diff(np.interp(np.arange(0.0, 99.0 + 1e-9, 10.0), t, smooth))
    assert share == pytest.approx(2 * 0.01**2 / np.mean(changes**2), rel=0.5)
    assert share < 0.01


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
