"""Range beacons (UWB): a bundle of beacon ranges with positions only is calibrated, not refused.

Issue 16 point 3: a UWB bundle with a model config (``config/default.toml``) was refused with
"no stream has a reference": the declared *sonar*'s range limits (``min_range_m``/``max_range_m``)
censored every UWB reading, and ``landmarks.csv`` required a bearing. The bundle here has a
known scale error and antenna offset, ``y = (1 + s) r + b + N(0, sigma^2)``.

Bounds: on white noise of known sigma the least-squares estimates of ``(b, s)`` on the fit part
have covariance ``sigma^2 (X^T X)^-1``, ``X = [1, r]`` over the fit part's true ranges; each
estimate must lie within 4 of its standard errors (two-sided false alarm 6e-5 per check).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.errors import BundleError
from koala_bridge.calibration.model import declared_model, read_config
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.problem import SkippedStream, Split
from koala_bridge.calibration.synthetic_beacons import (
    UwbCase,
    beacon_positions,
    make_uwb_bundle,
    uwb_truth,
)

ROOT = Path(__file__).parents[2]
Z = 4.0


def _ls_standard_errors(case: UwbCase) -> tuple[float, float]:
    """SE of (offset, scale) of least squares on the fit part's readings (module docstring)."""
    t, x, y = uwb_truth(case)
    fit = Split.of(t).mask(t, "fit")
    r = np.concatenate([np.hypot(x[fit] - bx, y[fit] - by) for bx, by in beacon_positions(case)])
    X = np.column_stack([np.ones_like(r), r])
    cov = case.noise_m**2 * np.linalg.inv(X.T @ X)
    return float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))


@pytest.mark.parametrize("form", ["landmarks", "range"])
def test_uwb_scale_and_offset_found(tmp_path: Path, form: str) -> None:
    case = UwbCase()
    bundle = load_bundle(make_uwb_bundle(tmp_path / "uwb", 7, case, form))
    model = declared_model(read_config(ROOT / "config" / "default.toml"), bundle.meta)
    skipped: list[SkippedStream] = []
    results = calibrate(bundle, model, skipped=skipped)
    assert [r.problem.name for r in results] == ["range:uwb"]
    assert skipped == []  # every stream of the bundle is the one calibrated
    res = results[0]
    assert res.problem.section == "sensors.uwb"
    params = {i.name: p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)}
    assert set(params) == {"bias", "scale"}, params
    se_b, se_s = _ls_standard_errors(case)
    assert se_b < 0.1 * case.offset_m and se_s < 0.1 * case.scale  # the bounds can fail
    assert abs(params["bias"]["bias"] - case.offset_m) < Z * se_b
    assert abs(params["scale"]["scale_error"] - case.scale) < Z * se_s
    # held out: before, the offset and scale (~0.25 m); after, the noise alone
    n = res.problem.residuals([], np.empty(0), "score").size
    assert res.before > 3 * case.noise_m
    assert res.after < case.noise_m * (1 + Z / np.sqrt(2 * n))


def test_far_uwb_beacons_are_not_censored_by_the_sonar(tmp_path: Path) -> None:
    """Beacons 12 m apart: every true range is beyond the declared sonar's max_range_m."""
    case = UwbCase(side_m=12.0)
    bundle = load_bundle(make_uwb_bundle(tmp_path / "uwb", 3, case, "range"))
    model = declared_model(read_config(ROOT / "config" / "default.toml"), bundle.meta)
    t, x, y = uwb_truth(case)
    nearest = min(float(np.hypot(x - bx, y - by).min()) for bx, by in beacon_positions(case))
    assert model.sonar_range_m is not None and nearest > model.sonar_range_m[1]
    results = calibrate(bundle, model)
    assert [r.problem.name for r in results] == ["range:uwb"]
    assert results[0].problem.t.size == 4 * t.size  # nothing dropped


def test_landmarks_need_a_range_or_a_bearing(tmp_path: Path) -> None:
    d = make_uwb_bundle(tmp_path / "uwb", 1, UwbCase(duration_s=5.0))
    text = (d / "landmarks.csv").read_text().replace("t,landmark_id,range", "t,landmark_id,rng")
    (d / "landmarks.csv").write_text(text)
    with pytest.raises(BundleError, match="range or bearing"):
        load_bundle(d)


def test_beacons_without_positions_are_skipped_with_a_reason(tmp_path: Path) -> None:
    d = make_uwb_bundle(tmp_path / "uwb", 2, UwbCase(duration_s=10.0))
    (d / "landmark_map.csv").unlink()
    bundle = load_bundle(d)
    skipped: list[SkippedStream] = []
    assert calibrate(bundle, declared_model({}, bundle.meta), skipped=skipped) == []
    assert [(s.stream, "landmark_map.csv" in s.missing) for s in skipped] == [("range:uwb", True)]
