"""IR readings closer than a declared response curve's first point are set aside.

A curve declared as a table from ``r0 > 0`` (a Sharp ranger's datasheet starts at 10 cm) says
nothing closer than ``r0``: the output there folds back. A reading at 5 cm, far off the table
held flat, must neither decide the fitted offset nor vanish unreported.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import calibrate
from koala_bridge.calibration.problem import SkippedStream

XS = [0.10, 0.20, 0.40, 0.80, 1.50]
YS = [450.0, 500.0, 300.0, 160.0, 90.0]
CONFIG = {"sensors": {"ir": {"ideal": False, "response_range_m": XS, "response_counts": YS}}}
OFFSET = -20.0  # counts: the effect to find
SIGMA = 2.0


def _bundle(tmp_path: Path, near: list[float]) -> Path:
    rng = np.random.default_rng(7)
    r = np.tile(np.linspace(0.12, 1.5, 60), 3)
    y = np.interp(r, XS, YS) + OFFSET + rng.normal(0, SIGMA, r.size)
    r = np.r_[np.asarray(near), r]
    y = np.r_[np.full(len(near), 250.0), y]  # folded back: 200 counts under the flat table
    d = tmp_path / "ir"
    d.mkdir()
    rows = "\n".join(
        f"{k},0,ir,{yk:.3f},{rk:.4f}" for k, (yk, rk) in enumerate(zip(y, r, strict=True))
    )
    (d / "range.csv").write_text("t,sensor,kind,measured,true_range\n" + rows + "\n")
    (d / "meta.json").write_text(json.dumps({"units": {"range_ir": "counts"}}))
    return d


def test_readings_closer_than_the_curve_are_set_aside_and_reported(tmp_path: Path) -> None:
    bundle = load_bundle(_bundle(tmp_path, near=[0.05, 0.05, 0.06]))
    (res,) = calibrate(bundle, declared_model(CONFIG, bundle.meta))
    assert any("3 readings at true ranges closer" in n for n in res.problem.notes)
    (bias,) = (p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)
               if i.name == "bias")
    # the offset of the other 180 readings: SE = 2 / sqrt(108 fit readings) ~ 0.2 counts;
    # the three at 200 counts off would pull it by ~5 counts (3 x 200 / 111)
    assert bias["bias"] == pytest.approx(OFFSET, abs=5 * SIGMA / np.sqrt(108))


def test_a_stream_left_with_only_readings_closer_than_the_curve_says_why(
    tmp_path: Path,
) -> None:
    d = _bundle(tmp_path, near=[0.05] * 30)
    bundle = load_bundle(d)
    csv = (d / "range.csv").read_text().splitlines()
    (d / "range.csv").write_text("\n".join(csv[:31]) + "\n")  # the near readings only
    bundle = load_bundle(d)
    skipped: list[SkippedStream] = []
    assert calibrate(bundle, declared_model(CONFIG, bundle.meta), skipped=skipped) == []
    (s,) = skipped
    assert "closer than the declared IR response curve's first point" in s.missing
    assert "response_range_m" in s.fix
