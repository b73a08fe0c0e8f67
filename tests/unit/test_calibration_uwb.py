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


def _shift_ranges(bundle: Path, late_s: float) -> None:
    """Stamp the readings of ``landmarks.csv`` ``late_s`` later (their clock runs ahead)."""
    path = bundle / "landmarks.csv"
    lines = path.read_text(encoding="utf-8").splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        t, rest = line.split(",", 1)
        out.append(f"{float(t) + late_s:.4f},{rest}")
    path.write_text("\n".join(out) + "\n", encoding="utf-8")


def _uwb(bundle: Path, effects: list[str] | None = None) -> list[str]:
    from koala_bridge.calibration.pipeline import Options

    b = load_bundle(bundle)
    (res,) = calibrate(b, declared_model({}, b.meta), Options(effects=effects))
    assert res.problem.name == "range:uwb"
    return list(res.problem.notes)


@pytest.mark.parametrize("late_s", [2.0, -3.0])
def test_ranges_on_a_clock_seconds_apart_are_said_to_be(tmp_path: Path, late_s: float) -> None:
    """A new user's lawn-mower log with its ranges 2 s late got a wrong scale and 9.8 times a
    hand fit's error, and no word: the readings' correlation with the true ranges of the robot
    shifted, searched as a scalar stream's clocks are, says how far they look apart."""
    case = UwbCase(duration_s=200.0)
    b = make_uwb_bundle(tmp_path / "b", 1, case)
    _shift_ranges(b, late_s)
    notes = _uwb(b)
    said = [n for n in notes if n.startswith("the readings match the reference best")]
    assert len(said) == 1, notes
    tau = float(said[0].split(" best ")[1].split(" s later")[0])
    # the coarse grid's step: reach / 50 steps, reach = min(10 s, 10 % of the fit part)
    assert abs(tau - late_s) <= 0.1 * 0.6 * 200.0 / 50, said
    dropped = [n for n in notes if "outside truth_pose.csv's time span" in n]
    assert len(dropped) == 1 and dropped[0].startswith(f"{int(abs(late_s) * 4 * 10)} readings")


def test_ranges_on_one_clock_are_not_said_to_be_apart(tmp_path: Path) -> None:
    notes = _uwb(make_uwb_bundle(tmp_path / "b", 1, UwbCase(duration_s=200.0)))
    assert not any(n.startswith("the readings match the reference best") for n in notes)
    assert not any("outside truth_pose.csv" in n for n in notes)


def test_an_effect_asked_for_and_not_tried_is_said_why(tmp_path: Path) -> None:
    notes = _uwb(make_uwb_bundle(tmp_path / "b", 1, UwbCase()), ["time_offset", "scale"])
    said = [n for n in notes if n.startswith("time_offset asked for (--effects) but not tried")]
    assert len(said) == 1 and "computed per reading" in said[0], notes


def test_a_declared_beacon_model_the_tool_does_not_read_is_said(tmp_path: Path) -> None:
    """A new user declared the UWB scale in meta.json (``sensor.uwb.scale_error``): ignored
    without a word, and the tool then "found" the scale the user had declared."""
    b = make_uwb_bundle(tmp_path / "b", 1, UwbCase())
    (b / "meta.json").write_text('{"sensor": {"uwb": {"scale_error": 0.03, "name": "dw1000"}}}',
                                 encoding="utf-8")
    notes = _uwb(b)
    said = [n for n in notes if n.startswith("meta.json's sensor.uwb (scale_error = 0.03)")]
    assert len(said) == 1 and "is not read" in said[0], notes
