"""A still gyro whose noise changes over time: a new user's MPU-6050 bolted to a base that shook
while a motor ran (five times its noise for the first 300 s). Every residual counted alike, the
vibrating stretch drowned the bias the quiet one shows: it passed the held-out test 94 times
over chance yet failed the fit part's BIC, and the report said "unchanged" where a hand bias
cut the held-out heading error by 38 %. Where the residual's variance differs between blocks
beyond chance (the Brown-Forsythe test) the likelihoods are taken per block, each with its own
variance (``selection.variance_blocks``, ``selection._log_ratio``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream, gyro_bundle
from koala_bridge.calibration.selection import _log_ratio, brown_forsythe, variance_blocks
from koala_bridge.calibration.synthetic import DECLARED

BIAS = 2e-4


def _still(tmp_path: Path, seed: int, shaking_s: float) -> Path:
    """1000 s at 100 Hz, still against a constant heading: ``BIAS``, 0.002 rad/s of noise, and
    0.012 rad/s more over the first ``shaking_s`` seconds."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 1000.0, 0.01)
    sd = np.where(t < shaking_s, np.hypot(0.002, 0.012), 0.002)
    return gyro_bundle(tmp_path / f"b{seed}", t, np.zeros_like(t),
                       BIAS + sd * rng.standard_normal(t.size))


@pytest.mark.parametrize("seed", range(5))
def test_a_bias_beside_a_vibrating_stretch_is_found(tmp_path: Path, seed: int) -> None:
    """Per block, 18 of 20 seeds name ``bias`` and 2 ``bias_drift`` (the held-out part, quiet
    throughout, cannot tell a ramp through it from a step); one variance for all named it on 7
    of 20 and nothing on the rest."""
    res, _ = calibrate_stream(_still(tmp_path, seed, 250.0), "gyro", DECLARED)
    assert res is not None
    names = [i.name for i in res.effects]
    assert names in (["bias"], ["bias_drift"]), names
    if names == ["bias"]:
        ((p, se),) = res.effect_params()
        assert abs(p["bias"] - BIAS) < 4 * se["bias"], (p, se)


@pytest.mark.parametrize("seed", range(5))
def test_a_still_gyro_without_a_bias_gets_none(tmp_path: Path, seed: int) -> None:
    """The same vibrating stretch and no bias: the blocks' likelihoods name nothing (20 of 20
    seeds)."""
    d = _still(tmp_path, seed, 250.0)
    y = np.loadtxt(d / "gyro.csv", delimiter=",", skiprows=1)
    y[:, 1] -= BIAS
    np.savetxt(d / "gyro.csv", y, delimiter=",", header="t,yaw_rate", comments="", fmt="%.10g")
    res, _ = calibrate_stream(d, "gyro", DECLARED)
    assert res is not None and res.effects == []


def test_one_variance_is_one_block() -> None:
    """White noise of one variance: no blocks (Brown-Forsythe at 1e-3: over 200 seeds at most
    a few), and the log-likelihood ratio is the plain ``n ln(RSS_old / RSS_new)``."""
    hits = sum(variance_blocks(np.random.default_rng(s).normal(0.0, 1.0, 5000)) is not None
               for s in range(200))
    assert hits <= 3  # binomial(200, 1e-3): P(more than 3) < 1e-4
    rng = np.random.default_rng(0)
    old = rng.normal(0.0, 1.0, 5000)
    new = old - 0.01
    assert _log_ratio(old, new) == pytest.approx(5000 * np.log(np.dot(old, old) / np.dot(new, new)))


def test_a_change_of_variance_is_found_in_blocks() -> None:
    rng = np.random.default_rng(1)
    r = np.r_[rng.normal(0.0, 3.0, 1000), rng.normal(0.0, 1.0, 4000)]
    starts = variance_blocks(r)
    assert starts is not None
    # per block: the quiet blocks weigh as their own variance says
    new = r - 0.05
    sizes = np.diff(np.r_[starts, r.size])
    so = np.add.reduceat(r * r, starts)
    sn = np.add.reduceat(new * new, starts)
    assert _log_ratio(r, new, starts) == pytest.approx(float(np.dot(sizes, np.log(so / sn))))


@pytest.mark.parametrize("df", [3, 5])
def test_heavy_tails_of_one_spread_are_one_block(df: int) -> None:
    """Bartlett's test, which assumes normal residuals, rejected one variance on 213 of 300 t5
    series and on all t3 ones; the Brown-Forsythe test, about the blocks' medians, does not."""
    hits = sum(variance_blocks(np.random.default_rng(s).standard_t(df, 5000)) is not None
               for s in range(100))
    assert hits <= 2  # binomial(100, 1e-3): P(more than 2) < 2e-4


@pytest.mark.parametrize("seed", range(3))
def test_brown_forsythe_is_scipy_s_levene_about_the_median(seed: int) -> None:
    from scipy import stats

    rng = np.random.default_rng(seed)
    groups = [rng.standard_t(4, 60) * (1 + (i % 3)) for i in range(7)]
    assert brown_forsythe(groups) == pytest.approx(
        stats.levene(*groups, center="median").pvalue, rel=1e-12, abs=1e-300)


@pytest.mark.parametrize(("shaking_s", "said"), [(250.0, True), (0.0, False)])
def test_noise_that_changes_over_time_is_said_in_the_allan_section(
    tmp_path: Path, shaking_s: float, said: bool
) -> None:
    """A new user's still gyro, 5 times noisier for its first 250 s: its Allan N (5.3e-4) and
    --write-noise's density averaged the two stretches, 2.65 times the quiet one's, unsaid."""
    res, _ = calibrate_stream(_still(tmp_path, 0, shaking_s), "gyro", DECLARED)
    assert res is not None and res.noise is not None
    notes = [n for n in res.noise.notes if n.startswith("the residual's noise changes over time")]
    assert bool(notes) == said
