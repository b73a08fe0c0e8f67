"""Noise identification by Allan variance (bridge/calibration/allan.py, noise.py).

White rate noise of known density N and a rate random walk of known K are recovered within
bounds derived from the Allan variance's confidence (IEEE Std 952 Annex C.1): a point of the
curve made of M independent clusters has a relative standard deviation of its Allan variance of
sqrt(2 / (M - 1)); a term that is the fraction f of that point's Allan variance is read there
with a relative error of sqrt(2 / (M - 1)) / (2 f) (its coefficient is a square root). The bound
for each term is 4 times the best such reading over the curve's points, computed here from the
true N, K and the cluster counts, independently of the code's own standard errors.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture: fonts open before the leak check
from koala_bridge.calibration.allan import (
    FLICKER_FACTOR,
    allan_noise,
    octave_cluster_sizes,
    overlapping_adev,
)
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.noise import StreamNoise, noise_json, noise_markdown, plot_allan
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.report import write_report
from koala_bridge.calibration.stages import Stage

Z = 4.0
RATE_HZ = 100.0
N_TRUE = 1e-3  # rad/s/sqrt(Hz): per-sample sigma N sqrt(rate) = 0.01 rad/s
K_TRUE = 1e-4  # rad/s^2/sqrt(Hz): crossing of the N and K lines at sqrt(3) N / K = 17 s


@pytest.fixture(scope="module")
def _matplotlib_fonts_loaded(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Render an Allan plot once before the per-test leak check takes its baseline: matplotlib's
    font cache keeps the font files it has loaded open for the life of the process, by design
    (as in tests/integration/test_calibration_cli.py)."""
    rate = _gyro_noise(0, 60.0, N_TRUE, K_TRUE)
    fit = allan_noise(rate, 1 / RATE_HZ)
    assert fit is not None
    noise = StreamNoise("warm-up", "rad/s", 1 / RATE_HZ, rate.size, fit)
    plot_allan(noise, tmp_path_factory.mktemp("fonts") / "allan.png")


def _gyro_noise(seed: int, duration_s: float, n_density: float, k_rrw: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dt = 1 / RATE_HZ
    n = int(duration_s * RATE_HZ)
    white = rng.normal(0, n_density / np.sqrt(dt), n)
    walk = np.cumsum(rng.normal(0, k_rrw * np.sqrt(dt), n))
    return np.asarray(white + walk)


def _bound(n_samples: int, n_density: float, k_rrw: float) -> tuple[float, float]:
    """Relative bounds on N and K (module docstring)."""
    m = octave_cluster_sizes(n_samples)
    tau = m / RATE_HZ
    delta = np.sqrt(2 / (n_samples // m - 1))
    avar = n_density**2 / tau + k_rrw**2 * tau / 3
    share_n = n_density**2 / tau / avar
    share_k = k_rrw**2 * tau / 3 / avar
    return Z * float(np.min(delta / (2 * share_n))), Z * float(np.min(delta / (2 * share_k)))


def test_overlapping_adev_is_the_definition() -> None:
    """NIST SP 1065 eq. 11 (phase form) equals the definition on cluster means, every overlapping
    pair of adjacent clusters: sigma^2 = mean((ybar_(k+m) - ybar_k)^2) / 2."""
    y = np.random.default_rng(0).normal(size=101)
    m = np.array([1, 3, 7])
    _, sigma = overlapping_adev(y, 0.5, m)
    for mk, s in zip(m, sigma, strict=True):
        ybar = np.convolve(y, np.ones(mk) / mk, mode="valid")  # ybar_k, k = 0 .. n - m
        d = ybar[mk:] - ybar[:-mk]
        assert s == pytest.approx(np.sqrt(np.mean(d**2) / 2), rel=1e-12)


@pytest.mark.parametrize("seed", [1, 2])
def test_white_noise_and_rate_random_walk_recovered(seed: int) -> None:
    rate = _gyro_noise(seed, 3600.0, N_TRUE, K_TRUE)
    fit = allan_noise(rate, 1 / RATE_HZ)
    assert fit is not None
    bound_n, bound_k = _bound(rate.size, N_TRUE, K_TRUE)
    assert bound_n < 0.01 and bound_k < 0.5  # bounds that a wrong estimate can fail
    assert abs(fit.angle_random_walk / N_TRUE - 1) < bound_n
    assert abs(fit.rate_random_walk / K_TRUE - 1) < bound_k
    # the code's standard errors are the same reading, on the fitted values (within 2x either
    # way; approx(rel=1) let a zero standard error through)
    assert 0.5 < (fit.angle_random_walk_se / N_TRUE) / (bound_n / Z) < 2.0
    assert 0.5 < (fit.rate_random_walk_se / K_TRUE) / (bound_k / Z) < 2.0
    # the minimum lies near the crossing, sqrt(3) N / K = 17 s (within an octave either way),
    # where the curve is sqrt(2 N K / sqrt(3)): B read there is that / 0.664
    assert 17.3 / 2 < fit.bias_instability_tau < 17.3 * 2
    floor = np.sqrt(2 * N_TRUE * K_TRUE / np.sqrt(3)) / FLICKER_FACTOR
    assert fit.bias_instability == pytest.approx(floor, rel=0.25)


def test_white_noise_alone_has_no_rate_random_walk() -> None:
    """Without a walk, K must stay far below the K that the same record would resolve to 9 %."""
    rate = _gyro_noise(3, 3600.0, N_TRUE, 0.0)
    fit = allan_noise(rate, 1 / RATE_HZ)
    assert fit is not None
    assert fit.rate_random_walk < K_TRUE / 4
    assert abs(fit.angle_random_walk / N_TRUE - 1) < _bound(rate.size, N_TRUE, 1e-12)[0]


def test_too_short_a_series_has_no_curve() -> None:
    assert allan_noise(np.zeros(25), 0.01) is None  # 10 clusters of 1 and 2 only


@pytest.mark.usefixtures("_matplotlib_fonts_loaded")
def test_still_gyro_through_calibrate_reports_allan(tmp_path: Path) -> None:
    """A still gyro (truth heading 0) with white noise and a bias: report.json and report.md give
    the Allan terms of the stream's residual, the Allan plot is saved beside the residual plot."""
    duration = 600.0
    rate = 0.01 + _gyro_noise(4, duration, N_TRUE, 0.0)
    t = np.arange(rate.size) / RATE_HZ
    d = tmp_path / "still"
    d.mkdir()
    np.savetxt(
        d / "gyro.csv",
        np.column_stack([t, rate]),
        delimiter=",",
        header="t,yaw_rate",
        comments="",
        fmt="%.10g",
    )
    np.savetxt(
        d / "truth_pose.csv",
        np.column_stack([t[[0, -1]], np.zeros((2, 3))]),
        delimiter=",",
        header="t,x,y,theta",
        comments="",
        fmt="%.10g",
    )
    bundle = load_bundle(d)
    results = calibrate(bundle, declared_model({"sensors": {"gyro": {"ideal": True}}}, {}))
    (res,) = results
    assert res.noise is not None
    out = tmp_path / "out"
    write_report(out, [Stage(1, str(d), results)], "")
    doc = json.loads((out / "report.json").read_text())
    allan = doc["streams"][0]["allan"]
    n_hat = allan["angle_random_walk"]["value"]
    assert abs(n_hat / N_TRUE - 1) < _bound(rate.size, N_TRUE, 1e-12)[0]
    assert allan["angle_random_walk"]["unit"] == "rad/s/sqrt(Hz)"
    assert "allan" not in doc["streams"][1]  # the secondary metric's entry: once per stream
    assert (out / "allan_gyro.png").stat().st_size > 0
    assert "![gyro Allan deviation](allan_gyro.png)" in (out / "report.md").read_text()


def test_a_residual_without_noise_has_no_noise_terms() -> None:
    """A perfect reading (a constant rate against its exact reference) leaves a zero residual:
    no noise to identify, not a crash (the weights once overflowed to NaN)."""
    from koala_bridge.calibration.allan import allan_noise

    assert allan_noise(np.zeros(3000), 0.05) is None
    # a constant leaves rounding alone in the cluster means: finite terms at that level
    fit = allan_noise(np.full(3000, 0.5), 0.05)
    assert fit is None or max(fit.angle_random_walk, fit.rate_random_walk,
                              fit.bias_instability) < 1e-10


@pytest.mark.parametrize("seed", range(3))
def test_a_curve_the_three_lines_make_fits_them(seed: int) -> None:
    """White noise and a rate random walk: every point within the bar of the fitted lines, and
    the curve turns up after its minimum (a floor)."""
    fit = allan_noise(_gyro_noise(seed, 600.0, 0.01, 1e-3), 0.01)
    assert fit is not None and not fit.misfit and fit.floor_reached


def test_white_noise_alone_reaches_no_floor() -> None:
    """The curve falls to its longest tau: B read there is only an upper bound (a new user's
    still gyro: "minimum / 0.664 at 82 s", as if a floor had been reached)."""
    fit = allan_noise(np.random.default_rng(4).normal(0.0, 0.01, 60_000), 0.01)
    assert fit is not None and not fit.floor_reached


def test_a_correlated_process_is_said_to_be_off_the_lines() -> None:
    """White noise plus a Gauss-Markov process (5 s): the Allan curve has a bump no sum of the
    three lines makes; the fitted flat term sat 2-6 times above the measured points and nothing
    said so (a new user's vibrating base)."""
    rng = np.random.default_rng(1)
    n, dt = 100_000, 0.01
    a = np.exp(-dt / 5.0)
    z = rng.normal(0.0, 0.003 * np.sqrt(1 - a * a), n)
    gm = np.zeros(n)
    for i in range(1, n):
        gm[i] = a * gm[i - 1] + z[i]
    fit = allan_noise(rng.normal(0.0, 0.01, n) + gm, dt)
    assert fit is not None and fit.misfit
    noise = StreamNoise("gyro", "rad/s", dt, n, fit)
    text = "\n".join(noise_markdown(noise, None))
    assert "the three lines do not describe this curve" in text
    assert noise_json(noise)["lines_fit_the_curve"] is False


def _turning_gyro(tmp_path: Path, sign: float):  # noqa: ANN202 - a StreamResult
    from _bundles import calibrate_stream, gyro_bundle
    from koala_bridge.calibration.synthetic import DECLARED

    rng = np.random.default_rng(2)
    t = np.arange(0.0, 120.0, 0.01)
    w = 0.6 * np.sin(2 * np.pi * t / 9) + 0.3 * np.sin(2 * np.pi * t / 3.7)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    d = gyro_bundle(tmp_path / "b", t, theta, sign * w + rng.normal(0.0, 0.005, t.size))
    res, _ = calibrate_stream(d, "gyro", DECLARED)
    assert res is not None
    return res


def test_a_turning_gyro_s_terms_are_said_to_be_upper_bounds(tmp_path: Path) -> None:
    res = _turning_gyro(tmp_path, 1.0)
    assert res.noise is not None
    assert any("upper bounds on the sensor's" in n for n in res.noise.notes)


def test_a_residual_larger_than_the_readings_gets_no_allan_analysis(tmp_path: Path) -> None:
    """A sign-flipped gyro (the sign note said so): its residual is twice the motion, and its
    "rate random walk 1.06" and "bias instability 0.096 rad/s" were reported as noise."""
    res = _turning_gyro(tmp_path, -1.0)
    assert res.noise is None
    notes = res.problem.notes
    assert any(n.startswith("no Allan analysis: the residual varies more") for n in notes)


def test_a_still_gyro_always_gets_its_allan_analysis(tmp_path: Path) -> None:
    """A still gyro's residual is its readings less a constant: its spread equals theirs up to
    rounding, and a bare comparison dropped the analysis on 1.5 % of seeds ("misses something
    large"). The bar is 1.25 times the readings' spread."""
    from _bundles import calibrate_stream, gyro_bundle
    from koala_bridge.calibration.synthetic import DECLARED

    t = np.arange(0.0, 60.0, 0.01)
    for seed in range(20):
        rng = np.random.default_rng(seed)
        d = gyro_bundle(tmp_path / f"b{seed}", t, np.zeros_like(t),
                        0.003 + rng.normal(0.0, 0.002, t.size))
        res, _ = calibrate_stream(d, "gyro", DECLARED)
        assert res is not None and res.noise is not None, seed
