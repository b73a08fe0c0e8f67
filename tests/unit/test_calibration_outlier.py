"""Spurious readings (issue 16, "Robust statistics"): the ``outlier`` mixture effect and robust
least squares.

A sonar logged against its truth with 9 % short readings (floor and beam echoes, seeds/004:
``U(0.1 m, true range)``) and a temperature column that has no effect: the tool must name
``outlier:short`` and nothing else there, estimate the fraction within a binomial bound, and
report an inlier error at the noise sigma. Without the effect (plain least squares and the RSS
test) it named a spurious ``scale`` of about -4 % on every seed: the mean of the short readings,
``-p (r - 0.1) / 2``, grows with the range. Clean streams never get the effect.
"""

from __future__ import annotations

import csv
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.config_update import write_config
from koala_bridge.calibration.effects import available_effects, get_effect
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import Options, StreamResult, calibrate
from koala_bridge.calibration.robust import (
    MAD_TO_SIGMA,
    gaussian_logpdf,
    heavy_tailed,
    inlier_responsibility,
    mad_sigma,
    mixture_loglik,
)
from koala_bridge.calibration.selection import heldout_score, select_effects
from koala_bridge.calibration.streams import build_ranges
from koala_bridge.calibration.synthetic import (
    DECLARED,
    NOISE,
    SONAR_MAX_M,
    SONAR_MIN_M,
    Injected,
    make_bundle,
)
from scipy import stats

SHORT = 0.09
#: two-sided 1e-3: the bound of every statistical check here
Z = float(stats.norm.ppf(1 - 5e-4))


def _range(
    tmp_path: Path, seed: int, inj: Injected, options: Options | None = None
) -> StreamResult:
    bundle = load_bundle(make_bundle(tmp_path / f"b{seed}", seed, inj))
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta), options)
    return next(r for r in results if r.problem.name == "range")


def _params(res: StreamResult) -> dict[str, dict[str, float]]:
    return {i.name: p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)}


def _fraction_bound(p: float, n: int) -> float:
    """Z binomial standard errors of a fraction p estimated from n readings."""
    return Z * float(np.sqrt(p * (1 - p) / n))


@pytest.mark.parametrize("seed", (1, 2, 3))
def test_short_readings_are_named_as_outliers_and_nothing_else(tmp_path: Path, seed: int) -> None:
    res = _range(tmp_path, seed, Injected(sonar_short=SHORT, sonar_temperature=True))
    assert "temperature_c" in res.problem.covariate_names  # the covariate was a candidate
    params = _params(res)
    assert set(params) == {"outlier:short"}
    n_fit = res.problem.readings("fit").size
    p = params["outlier:short"]["probability"]
    assert abs(p - SHORT) <= _fraction_bound(SHORT, n_fit), (p, n_fit)
    # Inlier error on the held-out part at the noise sigma: the chi-square interval of the
    # inliers' RMS (about (1 - p) n_s of them) at two-sided 1e-3.
    (inlier,) = [m for m in res.secondary if m.metric == "inlier_rms_error"]
    n_in = (1 - SHORT) * res.problem.readings("score").size
    lo, hi = (np.sqrt(stats.chi2.ppf(q, n_in) / n_in) for q in (5e-4, 1 - 5e-4))
    assert lo * NOISE["sonar"] <= inlier.after <= hi * NOISE["sonar"], inlier
    # "after" is the RMS of every held-out reading: not flattered by the classification
    assert res.after > 10 * inlier.after
    assert res.after == pytest.approx(res.before)


def test_outliers_and_an_effect_are_fitted_jointly(tmp_path: Path) -> None:
    # EM refits the effect on the readings the mixture holds as inliers: recovered within the
    # synthetic cases' 10 % (>= 20 SE), the inlier error falls to the noise.
    res = _range(tmp_path, 1, Injected(sonar_short=SHORT, sonar_range_dependent=0.02))
    params = _params(res)
    assert set(params) == {"outlier:short", "range_dependent"}
    assert params["range_dependent"]["k_per_m2"] == pytest.approx(0.02, abs=0.002)
    (inlier,) = [m for m in res.secondary if m.metric == "inlier_rms_error"]
    assert inlier.after < 1.1 * NOISE["sonar"] < 0.5 * inlier.before


def test_short_readings_and_max_range_glitches_are_told_apart(tmp_path: Path) -> None:
    # outlier:uniform explains both at first; once glitch scores the max-range readings,
    # outlier:short replaces it (one mixture at most, swapped only on held-out evidence).
    res = _range(tmp_path, 1, Injected(sonar_short=SHORT, sonar_glitch=0.05))
    assert {i.name for i in res.effects} == {"glitch", "outlier:short"}


def test_robust_loss_keeps_a_spurious_scale_out_without_the_outlier_effect(
    tmp_path: Path,
) -> None:
    # Plain least squares named scale ~ -0.04 here (the short readings' mean grows with range).
    names = [n for n in available_effects() if n != "outlier"]
    res = _range(
        tmp_path,
        1,
        Injected(sonar_short=SHORT, sonar_temperature=True),
        Options(effects=names),
    )
    assert res.problem.robust_scale() is not None
    assert res.effects == []


def test_readings_at_any_range_are_uniform_outliers(tmp_path: Path) -> None:
    # The simulator's sonar glitch: U(min, max) whatever the true range.
    d = make_bundle(tmp_path / "b", 4, Injected())
    rows = list(csv.DictReader((d / "range.csv").open()))
    rng = np.random.default_rng(4)
    hit = rng.random(len(rows)) < 0.05
    value = rng.uniform(SONAR_MIN_M, SONAR_MAX_M, len(rows))
    for row, h, v in zip(rows, hit, value, strict=True):
        if h:
            row["measured"] = repr(float(v))
    with (d / "range.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    bundle = load_bundle(d)
    res = next(
        r
        for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
        if r.problem.name == "range"
    )
    params = _params(res)
    assert set(params) == {"outlier:uniform"}
    n_fit = res.problem.readings("fit").size
    # Spurious readings within a few sigma of the truth cannot be told from inliers:
    # about 2 * 3 sigma / (max - min) of them, a bias far below the bound.
    assert abs(params["outlier:uniform"]["probability"] - 0.05) <= _fraction_bound(0.05, n_fit)


@pytest.mark.parametrize("seed", (21, 22, 23, 24))
def test_clean_bundle_gets_no_outlier_effect(tmp_path: Path, seed: int) -> None:
    bundle = load_bundle(make_bundle(tmp_path / "b", seed, Injected(sonar_temperature=True)))
    for res in calibrate(bundle, declared_model(DECLARED, bundle.meta)):
        assert not any(i.effect.mixture for i in res.effects), (res.problem.name, res.effects)


def test_forced_outlier_candidate_is_rejected_on_clean_streams(tmp_path: Path) -> None:
    """The heavy-tail gate aside: the held-out mixture likelihood itself rejects an outlier
    fraction on clean data. Under the null, p = 0 is on the boundary, so the statistic is
    1/2 chi2_0 + 1/2 chi2_1 and its 1 % quantile is passed with probability 0.005; the practical
    size (1 % of the density's scale, about 0.02 n_s in L) is far beyond it: 0 of 12 expected."""
    outlier = get_effect("outlier")
    added = 0
    for seed in range(30, 42):
        bundle = load_bundle(make_bundle(tmp_path / f"b{seed}", seed, Injected()))
        (problem,) = build_ranges(bundle, declared_model(DECLARED, bundle.meta))
        cands = [
            EffectInstance(
                "outlier:short",
                outlier,
                ("probability", "inlier_sigma", "low"),
                (0.01, NOISE["sonar"], 0.0),
                data={"support": "short"},
            ),
            EffectInstance(
                "outlier:uniform",
                outlier,
                ("probability", "inlier_sigma", "low", "high"),
                (0.01, NOISE["sonar"], 0.0, 4.0),
                data={"support": "uniform"},
            ),
        ]
        sel = select_effects(problem, cands)
        added += len(sel.added)
        for trial in sel.rounds[0]:
            assert trial.lr < trial.lr_threshold or trial.relative_gain < 0.01, trial
    assert added == 0


def test_heldout_score_ranks_the_outlier_model_by_likelihood(tmp_path: Path) -> None:
    # For a backward check (before vs after): the RMS of every reading is the same with and
    # without the outlier effect, the held-out likelihood is not.
    res = _range(tmp_path, 1, Injected(sonar_short=SHORT))
    sel, problem = res.selection, res.problem
    assert heldout_score(problem, sel.after) == pytest.approx(heldout_score(problem, sel.before))
    before, after = (heldout_score(problem, f, likelihood=True) for f in (sel.before, sel.after))
    n_s = problem.readings("score").size
    # the selection's held-out statistic L = 2 n_s (before - after), scaled by the residuals'
    # effective share (1 - rho) / (1 + rho), passed its threshold
    ((_, trial),) = sel.added
    c = (1 - sel.rho) / (1 + sel.rho) if sel.rho > 0 else 1.0
    assert 2 * c * n_s * (before - after) == pytest.approx(trial.lr, rel=1e-6)
    assert trial.lr > trial.lr_threshold


def test_mixture_with_no_spurious_share_is_the_gaussian_likelihood() -> None:
    rng = np.random.default_rng(0)
    r = rng.normal(0, 0.3, 500)
    log_g = np.full(r.size, -np.log(4.0))
    assert mixture_loglik(r, 0.3, 0.0, log_g) == pytest.approx(
        float(np.sum(gaussian_logpdf(r, 0.3))), rel=1e-12
    )
    assert np.all(inlier_responsibility(r, 0.3, 0.0, log_g) == 1.0)
    # a reading that cannot be spurious (g = 0) is an inlier whatever p
    assert inlier_responsibility(np.array([5.0]), 0.3, 0.4, np.array([-np.inf]))[0] == 1.0


def test_mad_scale_ignores_a_spurious_share() -> None:
    rng = np.random.default_rng(1)
    n = 20_000
    r = rng.normal(0, 1.0, n)
    r[: n // 10] = rng.uniform(-50, 0, n // 10)
    # MAD's asymptotic relative SE is 1.166 / sqrt(n) (Rousseeuw & Croux 1993); the 10 %
    # contamination moves the median and the MAD by O(p): the population values of the mixture
    # 0.9 N(0, 1) + 0.1 U(-50, 0), solved below, within 5 SE.
    from scipy import optimize

    def cdf(x: float) -> float:
        return 0.9 * stats.norm.cdf(x) + 0.1 * min(max((x + 50) / 50, 0.0), 1.0)

    med = optimize.brentq(lambda m: cdf(m) - 0.5, -5, 5)
    mad = optimize.brentq(lambda d: cdf(med + d) - cdf(med - d) - 0.5, 1e-6, 10)
    se = 1.166 / np.sqrt(n)
    assert abs(mad_sigma(r[n // 10 :]) - 1) < 5 * se * np.sqrt(n / (n - n // 10))
    assert abs(mad_sigma(r) / (MAD_TO_SIGMA * mad) - 1) < 5 * se
    assert MAD_TO_SIGMA * mad > 1.05        # the contamination does move it


def test_heavy_tail_test_false_alarm_rate() -> None:
    """On Gaussian samples the test alarms at most at its level 0.01: over 100 samples
    P(X >= 6 | 100, 0.01) = 5e-4."""
    rng = np.random.default_rng(2)
    alarms = sum(heavy_tailed(rng.normal(0, 1, 3000)) for _ in range(100))
    assert alarms < 6
    # ... and finds a 1 % share of far readings every time
    x = rng.normal(0, 1, 3000)
    x[:30] = 20.0
    assert heavy_tailed(x)
    # ... unless the declared model already has that share
    assert not heavy_tailed(x, declared_fraction=0.012)


def test_unsimulated_tables_are_written_as_one_comment_line_each(tmp_path: Path) -> None:
    # An effect with several named parameters (outlier, covariate) once left its second and
    # later parameters as bare keys at the end of the written config.
    path = tmp_path / "new.toml"
    found = {"sensors.sonar.calibration.outlier_short": {"probability": 0.09, "low": 0.25}}
    write_config(path, {"robot": {"wheel_base_m": 0.3}}, found)
    text = path.read_text()
    assert tomllib.loads(text) == {"robot": {"wheel_base_m": 0.3}}
    (line,) = [ln for ln in text.splitlines() if "outlier_short" in ln]
    assert line.startswith("#") and "probability = 0.09" in line and "low = 0.25" in line


def test_the_log_shows_what_an_outlier_effect_improves(tmp_path: Path) -> None:
    """The RMS of every reading is unchanged by an outlier effect (it leaves the prediction as
    it was), so the log says what it improves: the held-out likelihood it was selected by."""
    from koala_bridge.calibration.report import metric_lines
    from koala_bridge.calibration.stages import Stage

    res = _range(tmp_path, 1, Injected(sonar_short=SHORT))
    lines = metric_lines(Stage(1, str(tmp_path), [res]), res)
    (line,) = [x for x in lines if "log-likelihood" in x]
    before, after = (float(v) for v in line.split(": ", 1)[1].split(" (")[0].split(" -> "))
    assert after < before


def _below_minimum(tmp_path: Path) -> StreamResult:
    """9 % short echoes down to 0.1 m under default.toml, which declares the sonar's
    min_range_m = 0.25 (a new user's trial)."""
    from _sim_support import default_config

    rng = np.random.default_rng(2)
    n = 3000
    true = rng.uniform(0.35, 2.0, n)
    measured = true + rng.normal(0.0, 0.01, n)
    short = rng.random(n) < SHORT
    measured[short] = rng.uniform(0.1, true[short])
    bundle_dir = tmp_path / "sonar"
    bundle_dir.mkdir()
    np.savetxt(bundle_dir / "range.csv",
               np.column_stack([np.arange(n) * 0.05, np.zeros(n), measured, true]),
               delimiter=",", header="t,sensor,measured,true_range", comments="", fmt="%.6f")
    bundle = load_bundle(bundle_dir)
    (res,) = calibrate(bundle, declared_model(default_config(), bundle.meta))
    return res


def test_short_readings_below_the_declared_minimum_are_still_outliers(tmp_path: Path) -> None:
    """Readings below the declared minimum were impossible under the mixture: p came out at a
    third of the truth and a spurious scale passed. The support now reaches 0 when the data read
    below the declared minimum: one outlier effect, nothing else."""
    res = _below_minimum(tmp_path)
    names = [i.name for i in res.effects]
    assert len(names) == 1 and names[0].startswith("outlier:"), names
    assert _params(res)[names[0]]["low"] == 0.0


@pytest.mark.xfail(strict=True, reason=(
    "with default.toml's sonar noise table (6.6 % of the range, the data's is 1 cm) the uniform "
    "support wins over the short one (held-out LR 4480 vs 4394) and its p is 0.121, 3.3 binomial "
    "SE over the injected 0.09"))
def test_short_readings_below_the_declared_minimum_are_named_short(tmp_path: Path) -> None:
    res = _below_minimum(tmp_path)
    params = _params(res)
    assert set(params) == {"outlier:short"}
    n_fit = res.problem.readings("fit").size
    assert abs(params["outlier:short"]["probability"] - SHORT) <= _fraction_bound(SHORT, n_fit)


def test_one_gross_error_makes_a_stream_heavy_tailed() -> None:
    """One reading beyond every Gaussian reading's reach (robust.GROSS_ALPHA: n 2 Phi(-z) <
    1e-6, about 6.1 sigmas among 3000) is a gross error the count beyond 4 sigmas misses (one
    such reading among 3000 is a Gaussian's 19 %). The count's test is switched off here
    (alpha 0) so that the gross one alone answers: over 100 Gaussian samples it alarms with
    probability 1e-4."""
    rng = np.random.default_rng(5)
    assert not any(heavy_tailed(rng.normal(0, 1, 3000), alpha=0.0) for _ in range(100))
    x = rng.normal(0, 1, 3000)
    x[7] = 4.5  # beyond 4 sigmas, within a Gaussian's reach
    assert not heavy_tailed(x)
    x[7] = -230.0  # a UWB's -11.1 m against a true 3.1 m, at 6 cm of noise
    assert heavy_tailed(x, alpha=0.0)
    # a declared share of spurious readings explains one, even one expected in 3000 readings
    # (the simulator's sonar declares 0.2 %: a recording of 499 readings held one 190 sigmas
    # out, and calling it gross got the simulator's own sonar an outlier effect)
    assert not heavy_tailed(x, declared_fraction=1 / 3000)


def test_a_corrupt_uwb_range_does_not_move_the_fit(tmp_path: Path) -> None:
    """A real UWB log (cjhhalla/RCV_uwb_dataset, sequence 5) held one range of -11.1 m against
    a true 3.1 m among 5630: in plain least squares it moved its anchor's offset by 2.2
    standard errors, unsaid. It is a gross error: the fit is robust, and the report says what
    was read below 0 m."""
    from koala_bridge.calibration.synthetic_beacons import UwbCase, make_uwb_bundle

    case = UwbCase()
    clean = make_uwb_bundle(tmp_path / "clean", 7, case, "range")
    corrupt = tmp_path / "corrupt"
    shutil.copytree(clean, corrupt)
    path = corrupt / "range.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[len(lines) // 4].split(",")  # in the fit part
    row[header.index("measured")] = "-11.12"
    lines[len(lines) // 4] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")
    fits = []
    for d in (clean, corrupt):
        bundle = load_bundle(d)
        (res,) = calibrate(bundle, declared_model({}, bundle.meta))
        fits.append({i.name: (p, se) for i, (p, se) in
                     zip(res.effects, res.effect_params(), strict=True)})
        notes = res.problem.notes
    assert set(fits[0]) == set(fits[1]) == {"bias", "scale"}
    for name, key in (("bias", "bias"), ("scale", "scale_error")):
        (a, se), (b, _) = fits[0][name], fits[1][name]
        assert abs(a[key] - b[key]) < se[key], name  # within one standard error
    assert any("1 reading(s) below 0 m kept (the lowest -11.12 m)" in n for n in notes)
