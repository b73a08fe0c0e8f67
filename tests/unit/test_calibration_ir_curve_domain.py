"""IR readings where the declared response curve is not single-valued are set aside.

A curve declared as a table from ``r0 > 0`` (a Sharp ranger's datasheet starts at 10 cm) says
nothing closer than ``r0``; a curve that rises to a peak and falls (the Sharp's peaks near
15 cm and folds back closer) is single-valued only from its peak
(:func:`koala_bridge.calibration.streams.ir_curve_start`). A reading there, off what the
falling branch's offset and gain describe, must neither decide the fitted offset nor vanish
unreported.
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
from koala_bridge.calibration.streams import ir_curve_start

XS = [0.10, 0.20, 0.40, 0.80, 1.50]
YS = [520.0, 500.0, 300.0, 160.0, 90.0]
CONFIG = {"sensors": {"ir": {"ideal": False, "response_range_m": XS, "response_counts": YS}}}
OFFSET = -20.0  # counts: the effect to find
SIGMA = 2.0


def _bundle(
    tmp_path: Path, near: list[float], near_counts: float = 250.0, xs: list[float] = XS,
    ys: list[float] = YS,
) -> Path:
    rng = np.random.default_rng(7)
    r = np.tile(np.linspace(0.12, 1.5, 60), 3)
    r = r[r >= ir_curve_start((xs, ys))]
    y = np.interp(r, xs, ys) + OFFSET + rng.normal(0, SIGMA, r.size)
    r = np.r_[np.asarray(near), r]
    y = np.r_[np.full(len(near), near_counts), y]  # folded back: far under the curve
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
    assert "closer than where the declared IR response curve is single-valued" in s.missing
    assert "response_range_m" in s.fix


def test_where_a_declared_curve_starts() -> None:
    assert ir_curve_start(None) == 0.0
    # the simulator's Koala curve: saturated flat from 0 m, then falling
    assert ir_curve_start(([0.0, 0.01, 0.05, 0.25], [1023, 1023, 470, 0])) == 0.0
    assert ir_curve_start(([0.10, 0.20, 1.5], [520, 500, 90])) == 0.10  # first point
    # rises to a peak at 0.15 m, then falls (the Sharp GP2Y0A02YK datasheet's shape); order of
    # the table does not matter
    assert ir_curve_start(([0.20, 0.10, 0.15, 1.5], [518, 469, 561, 92])) == 0.15


PEAKED_XS = [0.10, 0.20, 0.40, 0.80, 1.50]
PEAKED_YS = [450.0, 500.0, 300.0, 160.0, 90.0]


def test_readings_on_a_curves_rising_branch_are_set_aside(tmp_path: Path) -> None:
    # readings at 0.12-0.19 m, on the branch rising to the peak at 0.20 m, folded 150 counts
    # under the declared curve: without the rule they pull the offset by about 150 x 5 / 110
    near = [0.12, 0.14, 0.16, 0.18, 0.19]
    d = _bundle(tmp_path, near=near, near_counts=320.0, xs=PEAKED_XS, ys=PEAKED_YS)
    config = {"sensors": {"ir": {"ideal": False, "response_range_m": PEAKED_XS,
                                 "response_counts": PEAKED_YS}}}
    bundle = load_bundle(d)
    (res,) = calibrate(bundle, declared_model(config, bundle.meta))
    assert any("5 readings at true ranges closer than 0.2 m" in n for n in res.problem.notes)
    (bias,) = (p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)
               if i.name == "bias")
    n_fit = 0.6 * (len(bundle.get("range")["t"]) - len(near))
    assert bias["bias"] == pytest.approx(OFFSET, abs=5 * SIGMA / np.sqrt(n_fit))
