"""Columns and signs that are not sensor errors (a new-user trial on an MPU-6050 on a rotary rig).

* Another axis of the same chip that sees the same motion through a misalignment is the measured
  quantity through another channel, not a covariate of the error: its coefficient traded against
  the scale and wrote a gain of 0.55 into the config. It is not proposed, and a note says why;
  a column of its own (a temperature) still is.
* A reference whose sign convention is the opposite of the readings' gets a scale through zero:
  rejected, and the notes say what it means instead of calling it a near miss.
* A further metric of the stream made worse while the metric effects are chosen on improved is
  said in words.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _bundles import gyro_bundle
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.effects import get_effect
from koala_bridge.calibration.effects.covariate import MAX_CHANNEL_R2, fast_r2, line_r2
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import _note_secondary_worse, calibrate
from koala_bridge.calibration.problem import SecondaryMetric, split_params
from koala_bridge.calibration.selection import Selection, Trial, fit_model, parameter_se
from koala_bridge.calibration.streams import build_gyro
from koala_bridge.calibration.synthetic import DECLARED


def _rig(out: Path, seed: int, sign: float = 1.0, late_s: float = 0.0) -> Path:
    """120 s at 50 Hz: a turning rig's truth heading (``sign`` -1: the opposite convention), a
    yaw gyro (white noise 0.01 rad/s), its x axis seeing 1.5 % of the yaw rate through a
    misalignment (own noise 0.002 rad/s), and a temperature that drifts on its own."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 120.0 + 0.01, 0.02)
    w = 0.3 * np.sin(2 * np.pi * t / 7) + 0.6 * np.sin(2 * np.pi * t / 2.3 + 1.0)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    yaw = w + rng.normal(0, 0.01, t.size)
    rate_x = 0.015 * w + rng.normal(0, 0.002, t.size)
    temp = 25 + 2 * np.sin(2 * np.pi * t / 150) + rng.normal(0, 0.05, t.size)
    return gyro_bundle(out, t, sign * theta, yaw, t + late_s, rate_x=rate_x,
                       temperature_c=temp)


def test_a_covariate_that_rises_with_the_motion_but_not_with_each_reading_stays(
    tmp_path: Path,
) -> None:
    # A rate table steps its rate up and the chip warms as it goes: the temperature's levels
    # follow the readings (R^2 > 1/2), its increments within 0.5 s do not follow theirs. Its
    # bias per degree is a covariate; a gain in its place would be wrong.
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 300.0 + 0.01, 0.02)
    w = 0.2 * (1 + np.floor(t / 50)) + 0.1 * np.sin(2 * np.pi * t / 3.1)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    temp = (25 + 8 * (1 - np.exp(-t / 200)) + np.sin(2 * np.pi * t / 40)
            + rng.normal(0, 0.05, t.size))
    out = gyro_bundle(tmp_path / "b", t, theta,
                      w + 0.01 * (temp - 25) + rng.normal(0, 0.01, t.size), temperature_c=temp)
    bundle = load_bundle(out)
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    fit = res.problem.part("fit")
    assert line_r2(fit.columns["temperature_c"], fit.y) > MAX_CHANNEL_R2
    names = [i.name for i in res.effects]
    assert "covariate:temperature_c" in names and "scale" not in names
    after = res.selection.after
    k = after.insts.index(next(i for i in res.effects if i.name == "covariate:temperature_c"))
    c = float(split_params(res.problem, after.insts, after.x)[k][0])
    at = len(res.problem.nuisance_x0()) + sum(i.n_free for i in after.insts[:k])
    se = float(parameter_se(res.problem, after)[at])
    assert abs(c - 0.01) < 4 * se                    # the injected 0.01 rad/s per degC


def test_line_r2_is_the_squared_correlation() -> None:
    rng = np.random.default_rng(1)
    p = rng.normal(size=2000)
    assert abs(line_r2(3 * p - 1, p) - 1) < 1e-12
    # equal parts signal and independent noise of the same variance: R^2 = 1/2, within 4 SE of
    # the estimate (delta method: SE(r^2) ~ 2 r (1 - r^2) / sqrt(n) = 0.0158)
    assert abs(line_r2(p + rng.normal(size=2000), p) - 0.5) < 4 * 0.0158
    assert line_r2(np.ones(10), p[:10]) == 0.0
    assert line_r2(p[:2], p[:2]) == 0.0


@pytest.mark.parametrize("late_s", [0.0, -0.3])
def test_another_axis_of_the_same_motion_is_not_a_covariate(tmp_path: Path, late_s: float) -> None:
    # (the gyro's log stamped 0.3 s early: the axes still share its clock)
    bundle = load_bundle(_rig(tmp_path / "b", 3, late_s=late_s))
    problem = build_gyro(bundle, declared_model(DECLARED, bundle.meta))
    assert problem is not None
    names = [c.name for c in get_effect("covariate").propose(problem)]
    assert names == ["covariate:temperature_c"]     # its own variation: still a covariate
    (note,) = (n for n in problem.notes if n.startswith("covariate:rate_x not tried"))
    assert "follows the yaw rate readings, in level" in note
    fit = problem.part("fit")
    # rate_x = 0.015 w + noise 0.002 and the readings w + noise 0.01: R^2 of the levels about
    # var(w) / (var(w) + (0.002/0.015)^2 + 0.01^2), 0.9 here; over 0.3 s w moves far more than
    # either noise, and both channels see it
    assert line_r2(fit.columns["rate_x"], fit.y) > MAX_CHANNEL_R2
    assert fast_r2(fit.columns["rate_x"], fit.y, fit.t) > MAX_CHANNEL_R2
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    assert not any(i.name.startswith("covariate:rate_x") for i in res.effects)


def test_a_reference_of_the_opposite_sign_is_said_not_fitted(tmp_path: Path) -> None:
    bundle = load_bundle(_rig(tmp_path / "b", 4, sign=-1.0))
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    assert "scale" not in [i.name for i in res.effects]
    signs = [n for n in res.problem.notes if n.startswith("scale fitted as")]
    assert len(signs) == 1 and "the readings run against the reference yaw rate" in signs[0]
    # rejected as implausible, not a near miss "a longer recording would tell"
    assert not any(n.startswith("scale not added though") for n in res.problem.notes)
    scale_trials = [t for rnd in res.selection.rounds for t in rnd if t.name == "scale"]
    assert scale_trials and all(t.implausible and not t.passed for t in scale_trials)


def test_a_further_metric_made_worse_is_said(tmp_path: Path) -> None:
    bundle = load_bundle(_rig(tmp_path / "b", 5))
    problem = build_gyro(bundle, declared_model(DECLARED, bundle.meta))
    assert problem is not None
    (bias,) = get_effect("bias").propose(problem)
    base = fit_model(problem, [], problem.nuisance_x0())
    fit = fit_model(problem, [bias], problem.initial_vector([bias], base.x, []))
    trial = Trial("bias", 1, 0.0, 0.0, 0.0, 0.0, True, fit)
    sel = Selection(problem, base, fit, [(bias, trial)])
    heading = SecondaryMetric("heading_error_10s_window_rms", "rad", 0.02, 0.03)
    _note_secondary_worse(problem, sel, 0.4, 0.1, [heading])
    (note,) = (n for n in problem.notes if n.startswith("heading_error_10s_window_rms worse"))
    assert "with bias (0.02 -> 0.03 rad) while rms_rate_error improved" in note
    assert "whose response to fast motion" not in note      # the hint is about a scale
    (scale,) = (c for c in get_effect("scale").propose(problem))
    with_scale = Selection(problem, base, fit, [(scale, trial)])
    _note_secondary_worse(problem, with_scale, 0.4, 0.1, [heading])
    assert "with scale (0.02 -> 0.03 rad)" in problem.notes[-1]
    assert "whose response to fast motion" in problem.notes[-1]
    # a compass's heading against the declared gyro: the gyro hint is not its
    _note_secondary_worse(problem, sel, 0.4, 0.1, [
        SecondaryMetric("heading_error_vs_declared_gyro_rms", "rad", 0.02, 0.03)])
    assert "whose response to fast motion" not in problem.notes[-1]
    assert problem.notes[-1].startswith("heading_error_vs_declared_gyro_rms worse")
    # better, the same to 4 digits, or the metric itself not improved: nothing to say
    n = len(problem.notes)
    _note_secondary_worse(problem, sel, 0.4, 0.1,
                          [SecondaryMetric("heading_error_10s_window_rms", "rad", 0.03, 0.02)])
    _note_secondary_worse(problem, sel, 0.1, 0.4, [heading])
    _note_secondary_worse(problem, sel, 0.4, 0.1,
                          [SecondaryMetric("heading_error_10s_window_rms", "rad", 0.02, 0.020001)])
    assert len(problem.notes) == n


def test_a_scalar_time_offset_is_bounded_inside_its_search_and_odometry_is_not(
    tmp_path: Path,
) -> None:
    from koala_bridge.calibration.effects.time_offset import MAX_TIME_OFFSET_S, search_window
    from koala_bridge.calibration.synthetic import Injected, make_bundle

    bundle_dir = make_bundle(tmp_path / "b", 4, Injected(), duration_s=180)
    # the odometry logged on a clock 0.7 s late: a latency beyond any scalar stream's window
    odo = bundle_dir / "odometry.csv"
    head, *rows = odo.read_text().splitlines()
    ti = head.split(",").index("t")
    odo.write_text("\n".join([head] + [
        ",".join(repr(float(c) + 0.7) if k == ti else c for k, c in enumerate(r.split(",")))
        for r in rows]) + "\n")
    bundle = load_bundle(bundle_dir)
    results = {r.problem.name: r for r in calibrate(bundle, declared_model(DECLARED,
                                                                           bundle.meta))}
    odometry = results["odometry"]
    (tau,) = (i for i in odometry.effects if i.name == "time_offset")
    assert tau.effect.plausible(tau, np.array([0.7]))     # no bound for odometry
    after = odometry.selection.after
    (value,) = split_params(odometry.problem, after.insts, after.x)[after.insts.index(tau)]
    assert float(value) == pytest.approx(0.7, abs=0.02)
    # a scalar stream's: inside the grid's window (at most MAX_TIME_OFFSET_S) by a grid step
    gyro = results["gyro"].problem
    (cand,) = get_effect("time_offset").propose(gyro)
    step, span = search_window(gyro)
    assert span == MAX_TIME_OFFSET_S and cand.data["inside_s"] == span - step
    assert cand.effect.plausible(cand, np.array([span - step]))
    # at the edge the best may lie beyond; beyond it, half a period of something else
    assert not cand.effect.plausible(cand, np.array([-(span - step / 2)]))
    assert not cand.effect.plausible(cand, np.array([span + 2 * step]))
