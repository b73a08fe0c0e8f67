"""An IR ranger logged while the robot drives away from a wall (a new user's Turtlebot log:
a Sharp GP2Y0A21 against its true x): the split in time is a split in range.

- Without a declared curve, the curve fitted on the fit part's 0.10-0.50 m was held flat over
  the held-out 0.50-0.88 m, every candidate failed, and the report said "unchanged". A note now
  says how much of the held-out part lies beyond the curve, and why.
- With a declared curve, a gain found at 23 SE was "written as a comment: the simulator has no
  key for it". It is written as the curve's counts scaled (``[sensors.ir] response_counts``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream
from koala_bridge.calibration.config_update import found_keys

XS = [0.10, 0.20, 0.40, 0.80, 1.50]
YS = [520.0, 400.0, 250.0, 140.0, 80.0]
CONFIG = {"sensors": {"ir": {"ideal": False, "response_range_m": XS, "response_counts": YS}}}
GAIN = 1.09
SIGMA = 2.0


def _sweep(tmp_path: Path, far_m: float) -> Path:
    """Driving away from 0.12 m to ``far_m`` in 60 s at 10 Hz, the sensor's gain ``GAIN``."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 60.0, 0.1)
    r = 0.12 + (far_m - 0.12) * t / t[-1]
    y = GAIN * np.interp(r, XS, YS) + rng.normal(0.0, SIGMA, t.size)
    d = tmp_path / "ir"
    d.mkdir(parents=True)
    rows = "\n".join(f"{k:.2f},0,ir,{yk:.3f},{rk:.4f}" for k, yk, rk in zip(t, y, r, strict=True))
    (d / "range.csv").write_text("t,sensor,kind,measured,true_range\n" + rows + "\n")
    (d / "meta.json").write_text(json.dumps({"units": {"range.measured": "counts"}}))
    return d


def test_held_out_ranges_beyond_a_fitted_curve_are_said(tmp_path: Path) -> None:
    res, _ = calibrate_stream(_sweep(tmp_path, 0.9), "range:ir")
    assert res is not None
    (note,) = [n for n in res.problem.notes if "lie beyond the response curve" in n]
    assert note.startswith("100 % of the held-out readings' true ranges")
    assert "Record both parts over the same ranges" in note


def test_a_gain_of_a_declared_curve_is_written_as_its_counts(tmp_path: Path) -> None:
    res, _ = calibrate_stream(_sweep(tmp_path, 0.75), "range:ir", CONFIG)
    assert res is not None
    assert not any("lie beyond the response curve" in n for n in res.problem.notes)
    assert [i.name for i in res.effects] == ["scale"]
    ((params, se),) = res.effect_params()
    assert params["scale_error"] == pytest.approx(GAIN - 1, abs=4 * se["scale_error"])
    keys = found_keys([res])
    counts = keys["sensors.ir.response_counts"]
    np.testing.assert_allclose(counts, np.asarray(YS) * (1 + params["scale_error"]), rtol=1e-5)
    assert res.not_written() == [None]


@pytest.mark.parametrize(("units", "says"), [
    ({"range.measured": "counts", "range.true_range": "cm"},
     "true_range is declared in 'cm' (meta.json units) and read as metres"),
    ({"range.measured": "V", "range.true_range": "m"},
     "measured is declared in 'v' (meta.json units) and read as counts"),
])
def test_a_unit_other_than_the_one_read_is_said(tmp_path: Path, units: dict[str, str],
                                                says: str) -> None:
    d = _sweep(tmp_path, 0.75)
    (d / "meta.json").write_text(json.dumps({"units": units}))
    res, _ = calibrate_stream(d, "range:ir", CONFIG)
    assert res is not None
    assert any(n.startswith(says) for n in res.problem.notes), res.problem.notes
    res, _ = calibrate_stream(_sweep(tmp_path / "plain", 0.75), "range:ir", CONFIG)
    assert res is not None and not any("(meta.json units)" in n for n in res.problem.notes)
