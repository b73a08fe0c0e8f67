"""The six bundles bench/real_data converts from public measured data (tests/data/real,
PROVENANCE.md "Bundles converted here"), held against the hand fits of bench/hand_fits.py.

The bundles are not committed (data brought in by a snapshot fetch stays out of this
repository's commits): ``python -m bench.real_data`` writes them, and a test whose bundle is
absent is skipped. For each bundle: calibrate runs, every stream of the bundle is in the
results, the tool's *before* is the hand fit's (the same metric on the same split), and its
held-out *after* is within 1.1 x the hand fit's (the target of issue 16) with the effect the
hand fit names. The HAND_* figures are the output of ``python -m bench.hand_fits`` (fit on the
first 60 %, scored on the last 40 %), not tuned to the tool. Where the tool does not meet them
yet the test is ``xfail(strict=True)``, so that the fix shows up as an XPASS.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate

DATA = Path(__file__).parents[1] / "data" / "real"
TARGET = 1.1  # issue 16: tool held-out after <= 1.1 x the hand fit's

#: (before, after) of bench/hand_fits.py, held-out, in the tool's metric and unit.
HAND = {
    ("labyrinth_uwb", "range:uwb"): (0.1698, 0.1196),  # bias + scale, m
    ("labyrinth_uwb", "odometry"): (0.3503, 0.02777),  # distance + yaw scale (sign), m
    ("lias_uwb_trolley", "range:uwb"): (0.1980, 0.07254),  # scale + per-anchor/tag offset, m
    ("hcsr04_sweeps", "range:sonar"): (0.1543, 0.1422),  # bias + scale, robust loss, m
    ("mag_ellipsoid_bazhin", "compass"): (40.36, 2.140),  # hard + soft iron, %
    ("roomba_spin", "compass"): (19.67, 8.264),  # before: 3-D |m|; after: 2-D ellipse, %
    ("sharp_gp2y0a02_sweep", "range:ir"): (19.37, 2.026),  # bias + scale, rated range, counts
}

STREAMS = {
    "labyrinth_uwb": {"range:uwb", "odometry"},
    "lias_uwb_trolley": {"range:uwb"},
    "hcsr04_sweeps": {"range:sonar"},
    "mag_ellipsoid_bazhin": {"compass"},
    "roomba_spin": {"compass"},
    "sharp_gp2y0a02_sweep": {"range:ir"},
}

_cache: dict[str, dict[str, StreamResult]] = {}


def _results(name: str) -> dict[str, StreamResult]:
    if not (DATA / name / "meta.json").is_file():
        pytest.skip(f"bundle {name} not generated: python -m bench.real_data.convert_{name}")
    if name not in _cache:
        bundle = load_bundle(DATA / name)
        # A bundle whose declared curve only a config can state ships it (--config).
        toml = DATA / name / "declared_model.toml"
        config = tomllib.loads(toml.read_text()) if toml.is_file() else {}
        model = declared_model(config, bundle.meta)
        _cache[name] = {r.problem.name: r for r in calibrate(bundle, model)}
    return _cache[name]


def _effects(res: StreamResult) -> list[str]:
    return [i.name for i in res.effects]


def _params(res: StreamResult) -> dict[str, dict[str, float]]:
    return {i.name: p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)}


@pytest.mark.parametrize("name", sorted(STREAMS))
def test_every_stream_is_calibrated(name: str) -> None:
    res = _results(name)
    assert STREAMS[name] <= set(res), f"{name}: streams {sorted(res)}"
    meta = json.loads((DATA / name / "meta.json").read_text())
    assert meta["source"]["commit"] and meta["licence"]
    for stream in STREAMS[name]:
        r = res[stream]
        assert np.isfinite(r.before) and np.isfinite(r.after)
        assert r.after <= r.before  # after is never worse than the declared model


@pytest.mark.parametrize(("name", "stream"), [k for k in HAND if k[0] != "roomba_spin"])
def test_before_is_the_hand_fits_declared_error(name: str, stream: str) -> None:
    """Same metric, same split: the declared model's held-out error agrees with the hand fit's
    (which re-implements the metric: range RMS, windowed dead reckoning, |m| spread)."""
    assert _results(name)[stream].before == pytest.approx(HAND[name, stream][0], rel=0.01)


def _within_target(name: str, stream: str) -> None:
    res = _results(name)[stream]
    hand = HAND[name, stream][1]
    assert res.after <= TARGET * hand, f"tool {res.after:.4g} vs hand {hand:.4g}"


def test_labyrinth_uwb_range_bias_and_scale() -> None:
    """Hand fit: antenna-delay offset 0.053 m + scale 3.4 %; the tool's scale alone (6 %)
    reaches the same held-out error (0.121 vs 0.120 m, noise-dominated: 30 s of data)."""
    _within_target("labyrinth_uwb", "range:uwb")
    assert {"scale", "bias"} & set(_effects(_results("labyrinth_uwb")["range:uwb"]))


def test_labyrinth_uwb_odometry_wheels_swapped() -> None:
    """Under the readme's convention the robot turns the wrong way against the ground truth
    (hand fit: yaw scale -0.47: left/right swapped or a mirrored frame). ``wheel_base`` starts
    from the sign the fit part prefers, so it crosses the zero least squares could not."""
    res = _results("labyrinth_uwb")["odometry"]
    assert "wheel_base" in _effects(res)
    assert _params(res)["wheel_base"]["yaw_scale"] < 0
    assert res.after < 0.2 * res.before


@pytest.mark.xfail(strict=True, reason=(
    "the tool's wheel base alone leaves 0.0312 m held-out against the hand fit's 0.028 m (1.12 x),"
    " the hand fit's yaw scale alone the same 0.0312 m: its distance scale 0.975 improves the 3 "
    "held-out windows by 11 %, which 3 windows cannot show significant (LR 1.4 < 8.6)"))
def test_labyrinth_uwb_odometry_within_target() -> None:
    _within_target("labyrinth_uwb", "odometry")


def test_lias_uwb_trolley_per_anchor_and_tag_offsets() -> None:
    """Two-way ranging: every range carries the anchor's and the tag's antenna delay."""
    _within_target("lias_uwb_trolley", "range:uwb")
    names = set(_effects(_results("lias_uwb_trolley")["range:uwb"]))
    assert {"offset_per:sensor", "offset_per:tag"} <= names


def test_hcsr04_sweeps_held_out_error() -> None:
    _within_target("hcsr04_sweeps", "range:sonar")


@pytest.mark.xfail(strict=True, reason=(
    "9 % of the sonar readings are echoes off nearer objects (up to 80 cm short at 150 cm): "
    "the tool now names them (outlier:short, p 0.113) and a bias of -12.5 mm (inlier RMS "
    "18.6 -> 8.5 mm; all readings 0.154 -> 0.150 m against the hand fit's 0.142), but not the "
    "-2.7 % scale the robust hand fit finds, which the held-out readings do not support (median "
    "|e|: hand with it 12.8 mm, hand's offset alone 4.2, tool 6.5)"))
def test_hcsr04_sweeps_scale() -> None:
    res = _results("hcsr04_sweeps")["range:sonar"]
    assert "scale" in _effects(res)
    assert _params(res)["scale"]["scale_error"] == pytest.approx(-0.027, abs=0.005)


def test_mag_ellipsoid_bazhin_hard_and_soft_iron() -> None:
    _within_target("mag_ellipsoid_bazhin", "compass")
    res = _results("mag_ellipsoid_bazhin")["compass"]
    assert {"hard_iron", "soft_iron"} <= set(_effects(res))
    h = _params(res)["hard_iron"]
    # hand fit: (-68.1, 83.3, -133.4) counts
    assert np.allclose([h["dh_x"], h["dh_y"], h["dh_z"]], [-68.1, 83.3, -133.4], atol=3.0)


def test_roomba_spin_compass_fit_is_physical() -> None:
    """A spin about one axis cannot identify a 3-D hard iron: a sphere through a circle runs off
    along its normal (|h| ~ 1.3e6 gauss once, with a 3-D spread of 8e-6 %). The hard iron is
    plausible only within 3 max|m| (m = f + h bounds |h| by 2 max|m|), so the tool keeps to
    effects the data determine; its 3-D spread is then no collapse to zero. (The hand fit's 2-D
    ellipse on (mx, my) leaves 8.3 % of the *horizontal* spread, another metric.)"""
    res = _results("roomba_spin")["compass"]
    m = res.problem.m
    if "hard_iron" in _effects(res):
        h = _params(res)["hard_iron"]
        size = np.linalg.norm([h.get("dh_x", 0.0), h.get("dh_y", 0.0), h.get("dh_z", 0.0)])
        assert size <= 3 * np.max(np.linalg.norm(m, axis=1))
    assert 0.5 < res.after < res.before     # % spread: better, not collapsed


def test_sharp_gp2y0a02_sweep_offset() -> None:
    """The datasheet curve peaks at 15 cm and folds back closer: the 5 and 10 cm readings are
    set aside (streams.ir_curve_start), the offset is fitted on the single-valued branch."""
    _within_target("sharp_gp2y0a02_sweep", "range:ir")


def test_sharp_gp2y0a02_sweep_names_the_offset() -> None:
    assert "bias" in _effects(_results("sharp_gp2y0a02_sweep")["range:ir"])
