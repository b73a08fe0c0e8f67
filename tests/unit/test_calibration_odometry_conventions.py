"""Odometry logs converted by someone else (a new user's lawn-mower log, issue 16's "errors that
teach"): a wheel that counts backwards, a clock seconds off the reference's, a tick size
declared as metres per tick, and standard errors that do not hang on the reference's glitches.

Synthetic bundles (``calibration.synthetic``, 120 s at 20 Hz: a fit part of 72 s, 14 windows of
5 s) with their ``odometry.csv`` or ``meta.json`` changed the way such logs differ.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from _bundles import calibrate_stream
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model, meta_declared, without_declared
from koala_bridge.calibration.pipeline import StreamResult
from koala_bridge.calibration.problem import SkippedStream
from koala_bridge.calibration.selection import _cluster_se
from koala_bridge.calibration.streams import build_odometry
from koala_bridge.calibration.streams.odometry import reference_jumps
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle, write_columns

DURATION_S = 120.0


def _bundle(tmp_path: Path, seed: int = 1) -> Path:
    return make_bundle(tmp_path / f"b{seed}", seed, duration_s=DURATION_S)


def _rewrite_odometry(d: Path, shift_s: float = 0.0, left_sign: float = 1.0) -> None:
    with (d / "odometry.csv").open() as f:
        header = f.readline().strip()
    a = np.loadtxt(d / "odometry.csv", delimiter=",", skiprows=1)
    cols = header.split(",")
    a[:, cols.index("t")] += shift_s
    a[:, cols.index("left_ticks")] *= left_sign
    write_columns(d / "odometry.csv", header, list(a.T))


def _odometry(
    d: Path, config: dict | None = None
) -> tuple[StreamResult | None, list[SkippedStream]]:
    return calibrate_stream(d, "odometry", DECLARED if config is None else config)


def test_a_wheel_counting_backwards_is_named_with_the_column_to_negate(tmp_path: Path) -> None:
    """Before: the diameter ratio's fit ran to -1 and the run ended in a ZeroDivisionError."""
    d = _bundle(tmp_path)
    _rewrite_odometry(d, left_sign=-1.0)
    odo, skipped = _odometry(d)
    assert odo is None
    (skip,) = [s for s in skipped if s.stream == "odometry"]
    assert "a wheel counts backwards" in skip.missing
    assert "negate left_ticks" in skip.fix


def test_the_same_counts_forward_are_calibrated(tmp_path: Path) -> None:
    odo, skipped = _odometry(_bundle(tmp_path))
    assert odo is not None and not [s for s in skipped if s.stream == "odometry"]
    assert odo.problem.clock_offset == 0.0  # type: ignore[attr-defined]


def test_no_wheel_geometry_dead_reckons_nothing_rather_than_raising(tmp_path: Path) -> None:
    bundle = load_bundle(_bundle(tmp_path))
    problem = build_odometry(bundle, declared_model(DECLARED, bundle.meta), 5.0)
    assert problem is not None
    for change in ({"ratio": -1.0}, {"tpm": 0.0}, {"wheel_base": 0.0}):
        st = problem.state()
        for k, v in change.items():
            setattr(st, k, v)
        x, y, th = problem.dead_reckon(st)
        assert np.isnan(x).all() and np.isnan(y).all() and np.isnan(th).all()


@pytest.mark.parametrize("shift_s", [2.0, -3.0])
def test_a_clock_seconds_off_is_found_and_not_read_as_stalls(tmp_path: Path,
                                                             shift_s: float) -> None:
    """The odometry stamped ``shift_s`` late: least squares from 0 and the stall detector's
    +-0.5 s do not reach it (a mower's log 2 s off read as 21 % stalled, and no offset)."""
    d = _bundle(tmp_path)
    _rewrite_odometry(d, shift_s=shift_s)
    odo, _ = _odometry(d)
    assert odo is not None
    problem = odo.problem
    assert problem.clock_offset == pytest.approx(shift_s, abs=0.25)  # type: ignore[attr-defined]
    assert any("clock is about" in n for n in problem.notes)
    assert not problem.set_aside.spans  # type: ignore[attr-defined]
    # the offset first (odometry's false positives otherwise: a wheel_ratio of 1.3 SE on
    # seed 1 here, as on its clean 120 s bundle at seed 2, passes the held-out test unwritten)
    assert odo.effects[0].name == "time_offset"
    params, se = odo.effect_params()[0]
    assert abs(params["tau_s"] - shift_s) <= 3 * se["tau_s"], (params, se)
    assert odo.after <= odo.before / 3


def test_the_wheel_base_sign_is_judged_where_the_clocks_meet(tmp_path: Path) -> None:
    """A wheel base 6 % off and ticks 3 % off, the odometry stamped 3 s late: at no shift the
    declared model's fit part preferred the swapped wheels (-b), and the fit beside the time
    offset, started there, could not cross zero: no wheel base, and a heading drift of 0.7 SE
    in its place (a new user's log: wheel_base rejected, 2.3 times the hand fit's error)."""
    d = make_bundle(tmp_path / "b", seed=3, inj=Injected(wheel_base=0.06, tick_scale=0.03),
                    duration_s=300.0)
    for f in d.glob("*.csv"):
        if f.name not in ("truth_pose.csv", "odometry.csv"):
            f.unlink()
    _rewrite_odometry(d, shift_s=3.0)
    odo, _ = _odometry(d)
    assert odo is not None
    assert sorted(i.name for i in odo.effects) == ["tick_scale", "time_offset", "wheel_base"]
    truth = {"tau_s": 3.0, "wheel_base_m": 1.06 * DECLARED["robot"]["wheel_base_m"],
             "ticks_per_metre": 1.03 * DECLARED["robot"]["ticks_per_metre"]}
    for params, se in odo.effect_params():
        ((name, value),) = params.items()
        assert abs(value - truth[name]) <= 4 * se[name], (name, value, se)


def test_glitches_in_the_reference_do_not_shrink_the_standard_error(tmp_path: Path) -> None:
    """A time offset's standard error is at least the windows' jackknife, which does not hang
    on the residual's lag-1 autocorrelation; a few reference glitches took that from ~1 to ~0
    (a mower's SE fell 37-fold, and an 8-fold fall here). 0.4 % of the reference rows thrown
    0.5 m: the jackknife stays within a factor 1.5, and the SE reported is never below it."""
    ses, jackknife = [], []
    for glitch in (False, True):
        d = _bundle(tmp_path / str(glitch))
        _rewrite_odometry(d, shift_s=0.15)
        if glitch:
            with (d / "truth_pose.csv").open() as f:
                header = f.readline().strip()
            a = np.loadtxt(d / "truth_pose.csv", delimiter=",", skiprows=1)
            rng = np.random.default_rng(7)
            rows = rng.choice(a.shape[0], size=a.shape[0] // 250, replace=False)
            a[rows, 1] += 0.5
            write_columns(d / "truth_pose.csv", header, list(a.T))
        odo, _ = _odometry(d)
        assert odo is not None
        found = dict(zip((i.name for i in odo.effects), odo.effect_params(), strict=True))
        assert "time_offset" in found, [i.name for i in odo.effects]
        ses.append(found["time_offset"][1]["tau_s"])
        after = odo.selection.after
        labels = odo.problem.clusters("fit")
        assert labels is not None
        at = [i.name for i in after.insts].index("time_offset")
        jackknife.append(float(_cluster_se(after, labels)[at]))
        assert ses[-1] >= 0.999 * float(f"{jackknife[-1]:.3g}"), (ses, jackknife)
    assert 1 / 1.5 <= jackknife[1] / jackknife[0] <= 1.5, jackknife


def test_tick_size_declares_ticks_per_metre() -> None:
    meta = {"robot": {"tick_size_m": 1e-4, "wheel_base_m": 0.3}}
    model = declared_model({}, meta)
    assert model.ticks_per_metre == pytest.approx(1e4)
    assert meta_declared(meta)["robot.ticks_per_metre"] == pytest.approx(1e4)
    # a stage that found ticks_per_metre takes both forms of it out of the next bundle's meta
    assert "tick_size_m" not in without_declared(meta, {"robot.ticks_per_metre"})["robot"]
    # meta.json's own ticks_per_metre comes first; either form wins over the config
    both = {"robot": {"tick_size_m": 1e-4, "ticks_per_metre": 5000.0}}
    assert declared_model({}, both).ticks_per_metre == 5000.0
    config = {"robot": {"ticks_per_metre": 7000.0}}
    assert declared_model(config, meta).ticks_per_metre == pytest.approx(1e4)


def test_a_wheel_diameter_alone_says_what_it_lacks(tmp_path: Path) -> None:
    d = _bundle(tmp_path)
    meta = json.loads((d / "meta.json").read_text())
    meta["robot"] = {"wheel_diameter_m": 0.085, "wheel_base_m": 0.3}
    (d / "meta.json").write_text(json.dumps(meta))
    odo, skipped = _odometry(d, config={})
    assert odo is None
    (skip,) = [s for s in skipped if s.stream == "odometry"]
    assert "wheel_diameter_m 0.085 alone" in skip.missing
    assert "ticks per wheel turn" in skip.fix


def test_jumps_of_the_reference_are_said() -> None:
    """A tracker that loses its markers for a sample: each glitch is a step out and one back,
    far above the robot's speed; a drive that merely speeds up is none."""
    t = np.arange(0.0, 60.0, 0.01)
    speed = 0.2 + 0.1 * np.sin(t / 5)
    p = np.column_stack([np.cumsum(speed) * 0.01, np.zeros_like(t)])
    assert reference_jumps(t, p) is None
    glitched = p.copy()
    glitched[[1000, 2500, 4000], 1] += 0.3  # 30 m/s for a sample
    note = reference_jumps(t, glitched)
    assert note is not None and note.startswith("the reference jumps: 6 of 5999 ")
    assert "first at t = 10, 10.01, 25" in note


def test_a_spin_with_the_marker_ahead_of_the_axle_is_no_backward_wheel(tmp_path: Path) -> None:
    """A robot turning on the spot with its tracker's marker 0.15 m ahead of the axle: the
    marker travels in circles, as far as the counts would with one wheel negated. The turns
    tell them apart (a reviewer's case: the stream was skipped, 'negate left_ticks')."""
    tpm, base, lever = 10000.0, 0.3, 0.15
    t = np.arange(0.0, 120.0, 0.05)
    w = 0.8 + 0.3 * np.sin(2 * np.pi * t / 13)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    turn = np.r_[0.0, np.diff(theta)]
    left = np.rint(np.cumsum(-turn * base / 2 * tpm))
    right = np.rint(np.cumsum(turn * base / 2 * tpm))
    d = tmp_path / "spin"
    d.mkdir()
    write_columns(d / "odometry.csv", "t,left_ticks,right_ticks", [t, left, right])
    write_columns(d / "truth_pose.csv", "t,x,y,theta",
                  [t, 1 + lever * np.cos(theta), 1 + lever * np.sin(theta), theta])
    (d / "meta.json").write_text(json.dumps({"robot": {"ticks_per_metre": tpm,
                                                       "wheel_base_m": base}}))
    odo, skipped = _odometry(d, config={})
    assert not [s for s in skipped if s.stream == "odometry"], [s.line() for s in skipped]
    assert odo is not None


def test_a_spin_on_the_axle_tries_no_tick_size(tmp_path: Path) -> None:
    """Turning on the spot with the tracker on the axle: the reference travels nowhere, and a
    tick size fitted there only shrank the slip the counts carry (9.5e6 ticks/m against the
    declared 1e4, standard error 5e-14, written)."""
    tpm, base = 10000.0, 0.3
    rng = np.random.default_rng(2)
    t = np.arange(0.0, 120.0, 0.05)
    w = 0.8 + 0.3 * np.sin(2 * np.pi * t / 13)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    turn = np.r_[0.0, np.diff(theta)]
    slip = rng.normal(0.0, 2e-4, (2, t.size))
    left = np.rint(np.cumsum((-turn * base / 2 + slip[0]) * tpm))
    right = np.rint(np.cumsum((turn * base / 2 + slip[1]) * tpm))
    d = tmp_path / "spin"
    d.mkdir()
    write_columns(d / "odometry.csv", "t,left_ticks,right_ticks", [t, left, right])
    write_columns(d / "truth_pose.csv", "t,x,y,theta", [t, 1 + 0 * t, 1 + 0 * t, theta])
    (d / "meta.json").write_text(json.dumps({"robot": {"ticks_per_metre": tpm,
                                                       "wheel_base_m": base}}))
    odo, _ = _odometry(d, config={})
    assert odo is not None
    assert any(n.startswith("tick_scale not tried: the reference travels 0 m")
               for n in odo.problem.notes)
    assert "tick_scale" not in [i.name for i in odo.effects]
