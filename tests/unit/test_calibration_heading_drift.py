"""``heading_drift`` (issue 16, point 3): odometry whose dead-reckoned heading turns at a constant
rate relative to the truth.

Synthetic bundles (``calibration.synthetic``, 60 s at 20 Hz) with ``heading_drift = 0.03 rad/s``
injected as opposite tick streams. Over 30 clean seeds (100-129) the fitted drift scatters by
0.0011 rad/s, so 0.03 is 27 of those; there the held-out 5 s window error falls by 6-17x (at
most 0.17 of *before*) and the fitted value lies within 2.3 of the tool's own standard errors.
The bounds below: the value within 3 of its reported SE and within 10 % (the rule of the
synthetic cases, >= 2 SE); the error after at most a third of the error before (the issue's
hand fit). Without the drift, the same seeds' odometry gets no effect.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.config_update import found_keys
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle

DRIFT = 0.03  # rad/s
SEEDS = (1, 2, 3)


def _odometry(tmp_path: Path, seed: int, drift: float) -> StreamResult:
    bundle = load_bundle(make_bundle(tmp_path / f"b{seed}", seed, Injected(heading_drift=drift)))
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta))
    (odo,) = (r for r in results if r.problem.name == "odometry")
    return odo


@pytest.mark.parametrize("seed", SEEDS)
def test_heading_drift_is_found_and_removes_most_of_the_error(tmp_path: Path, seed: int) -> None:
    odo = _odometry(tmp_path, seed, DRIFT)
    assert [i.name for i in odo.effects] == ["heading_drift"]
    ((params, se),) = odo.effect_params()
    rate, rate_se = params["rate_rad_s"], se["rate_rad_s"]
    assert abs(rate - DRIFT) <= 3 * rate_se, (rate, rate_se)
    assert abs(rate - DRIFT) <= 0.1 * DRIFT, rate
    assert odo.after <= odo.before / 3, (odo.before, odo.after)
    assert found_keys([odo]) == {"sensors.odometry.calibration.heading_drift_rad_s": rate}


@pytest.mark.parametrize("seed", (2, 3))
def test_heading_drift_is_found_beside_tick_scale_and_wheel_base(tmp_path: Path, seed: int) -> None:
    """The issue's robot: tick size, wheel base and a drift at once. 120 s: on 60 s, after the
    wheel base each of the other two gains ~30 % held out but its LR (7-8) stays below the
    threshold (9.1) on the five held-out windows, and the drift is named on 1 seed in 5."""
    inj = Injected(tick_scale=0.05, wheel_base=0.1, heading_drift=DRIFT)
    bundle = load_bundle(make_bundle(tmp_path / "b", seed, inj, duration_s=120.0))
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta))
    (odo,) = (r for r in results if r.problem.name == "odometry")
    found = {i.name: p for i, (p, _) in zip(odo.effects, odo.effect_params(), strict=True)}
    assert set(found) == {"tick_scale", "wheel_base", "heading_drift"}
    assert found["heading_drift"]["rate_rad_s"] == pytest.approx(DRIFT, abs=0.1 * DRIFT)
    assert found["tick_scale"]["ticks_per_metre"] == pytest.approx(10500.0, abs=50.0)
    assert found["wheel_base"]["wheel_base_m"] == pytest.approx(0.33, abs=0.003)
    assert odo.after <= odo.before / 3


@pytest.mark.parametrize("seed", SEEDS)
def test_clean_odometry_gets_no_heading_drift(tmp_path: Path, seed: int) -> None:
    odo = _odometry(tmp_path, seed, 0.0)
    assert odo.effects == []
