"""Spurious sonar readings injected into a simulator recording, calibrated against
``config/default.toml`` (the ``outlier`` effect, docs/calibration.md "Spurious readings").

The simulated sonar's noise is the declared distance-error table (6.6 % of the range beyond 1 m),
so the inlier noise is heteroscedastic: the mixture's inlier sigma is a multiple of the declared
sigma per reading, and here it must come out at 1. 9 % of the sonar readings that had an echo are
replaced by a short reading ``U(min_range_m, true range)`` (floor and beam echoes) or by one
``U(min_range_m, max_range_m)`` (the simulator's own glitch model, whose key it then writes).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _sim_inject import _sonar
from _sim_support import default_config
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.config_update import found_keys
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.recording.export import export_bundle
from koala_bridge.tools.sim_recording import record_simulator
from scipy import stats

SHARE = 0.09
MIN_M, MAX_M = 0.25, 2.5  # [sensors.sonar] min_range_m, max_range_m of default.toml
Z = float(stats.norm.ppf(1 - 5e-4))  # two-sided 1e-3 per check


@pytest.fixture(scope="module")
def config() -> dict[str, Any]:
    return default_config()


@pytest.fixture(scope="module")
def recording(config: dict[str, Any], tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("outlier_sim")
    mcap = record_simulator(config, tmp / "run.mcap", 60.0, seed=3, pose_rate_hz=100.0)
    return export_bundle(mcap, tmp / "clean")


def _inject(
    recording: Path, out: Path, spurious: Callable[[np.random.Generator, np.ndarray], np.ndarray]
) -> Path:
    shutil.copytree(recording, out)
    table, sonar = _sonar(out)
    y, true_range = table["measured"], table["true_range"]
    rng = np.random.default_rng(7)
    hit = sonar & np.isfinite(y) & (rng.random(y.size) < SHARE)
    y[hit] = spurious(rng, true_range)[hit]
    table["measured"] = y
    table.save()
    return out


def _sonar_result(path: Path, config: dict[str, Any]) -> tuple[StreamResult, dict[str, Any]]:
    bundle = load_bundle(path)
    results = calibrate(bundle, declared_model(config, bundle.meta))
    (res,) = [r for r in results if r.problem.name == "range:sonar"]
    return res, found_keys(results)


def _check_mixture(res: StreamResult, name: str, share: float) -> dict[str, float]:
    assert [i.name for i in res.effects] == [name]
    ((params, _),) = res.effect_params()
    n = res.problem.readings("fit").size
    assert abs(params["probability"] - share) <= Z * np.sqrt(share * (1 - share) / n), params
    # the declared table is the simulator's noise: the fitted multiple of it is 1 within the
    # chi-square interval of about (1 - p) n inliers
    n_in = (1 - share) * n
    lo, hi = (np.sqrt(stats.chi2.ppf(q, n_in) / n_in) for q in (5e-4, 1 - 5e-4))
    assert lo <= params["inlier_sigma_ratio"] <= hi, params
    return params


def test_short_readings_in_a_simulator_recording(
    recording: Path, config: dict[str, Any], tmp_path: Path
) -> None:
    path = _inject(
        recording, tmp_path / "short", lambda rng, r: MIN_M + (r - MIN_M) * rng.random(r.size)
    )
    res, keys = _sonar_result(path, config)
    params = _check_mixture(res, "outlier:short", SHARE)
    assert params["low"] == MIN_M
    assert "sensors.sonar.glitch_probability" not in keys  # a different model from the sim's


def test_readings_at_any_range_write_the_simulators_glitch_probability(
    recording: Path, config: dict[str, Any], tmp_path: Path
) -> None:
    path = _inject(recording, tmp_path / "any", lambda rng, r: rng.uniform(MIN_M, MAX_M, r.size))
    res, keys = _sonar_result(path, config)
    # the declared glitch_probability (0.002) draws from the same distribution
    share = SHARE + 0.002
    params = _check_mixture(res, "outlier:uniform", share)
    assert (params["low"], params["high"]) == (MIN_M, MAX_M)
    assert keys["sensors.sonar.glitch_probability"] == pytest.approx(params["probability"])
