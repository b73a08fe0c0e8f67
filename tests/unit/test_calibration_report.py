"""What the calibration report tells (issue 16): robust held-out errors, a change that a sign
cannot fake, every stream of the input (calibrated, or what it lacks and how to add it), and no
effect written whose uncertainty is larger than it.

Bundles are built in tmp_path: a few small CSV files, fixed seeds.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from _mpl import fonts_loaded  # noqa: F401 - autouse fixture: fonts open before the leak check
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.config_update import found_keys
from koala_bridge.calibration.effects import get_effect
from koala_bridge.calibration.errors import BundleError
from koala_bridge.calibration.metrics import (
    MAD_TO_SIGMA,
    change,
    error_statistics,
    heldout_statistics,
    robust_sigma,
)
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import WRITE_Z, StreamResult, calibrate
from koala_bridge.calibration.problem import SecondaryMetric, SkippedStream
from koala_bridge.calibration.report import metric_text, report_json, report_markdown
from koala_bridge.calibration.selection import Selection, fit_model, judge, parameter_se
from koala_bridge.calibration.stages import Stage
from koala_bridge.calibration.streams import build_gyro
from koala_bridge.calibration.synthetic import DECLARED, Injected, make_bundle
from koala_bridge.cli import calibrate as cli

DEFAULT_TOML = Path(__file__).parents[2] / "config" / "default.toml"


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    return parser.parse_args([*argv, "--quiet", "--no-plots"])


def _csv(path: Path, header: str, *cols: np.ndarray) -> None:
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=header, comments="", fmt="%.10g")


def _gyro_bundle(
    out: Path, seed: int, bias: float = 0.0, meta: Mapping[str, object] | None = None
) -> Path:
    """60 s at 20 Hz: a turning robot's truth heading and a gyro (white noise 0.005 rad/s) that
    reads the true rate plus ``bias``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 60.0 + 0.025, 0.05)
    w = 0.2 + 0.5 * np.sin(2 * np.pi * t / 11)
    theta = np.r_[0.0, np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    out.mkdir(parents=True)
    _csv(out / "truth_pose.csv", "t,x,y,theta", t, t * 0 + 1, t * 0 + 1, theta)
    _csv(out / "gyro.csv", "t,yaw_rate", t, w + bias + rng.normal(0, 0.005, t.size))
    (out / "meta.json").write_text(json.dumps(meta or {}), encoding="utf-8")
    return out


# --- metrics on known vectors ----------------------------------------------------------------


def test_statistics_of_a_known_error_vector() -> None:
    after = np.array([-3.0, -1.0, 0.0, 1.0, 3.0, 100.0])
    # median 0.5; |r - 0.5| = 3.5 1.5 0.5 0.5 2.5 99.5, MAD 2.0: sigma 2.9652, 5 sigma 14.826
    assert robust_sigma(after) == pytest.approx(MAD_TO_SIGMA * 2.0)
    before = np.array([10.0, 20.0, -20.0, 30.0, 12.0, 11.0])
    # median 11.5; |r - 11.5| = 1.5 8.5 31.5 18.5 0.5 0.5: two beyond 14.826
    st = heldout_statistics(before, after)
    assert st.n == 6 and st.threshold == pytest.approx(5 * 1.4826 * 2.0)
    a, b = st.after, st.before
    assert a.rms == pytest.approx(np.sqrt(10020 / 6))
    assert a.median_abs == pytest.approx(2.0)  # |r| sorted 0 1 1 3 3 100
    assert a.p95_abs == pytest.approx(3 + 0.75 * 97)  # position 0.95 * 5 = 4.75, linear
    assert a.outlier_fraction == pytest.approx(1 / 6)  # the 100
    assert b.rms == pytest.approx(np.sqrt((100 + 400 + 400 + 900 + 144 + 121) / 6))
    assert b.median_abs == pytest.approx(16.0)  # |r| sorted 10 11 12 20 20 30
    assert b.outlier_fraction == pytest.approx(2 / 6)
    assert json.dumps(a.as_dict())  # finite numbers, JSON-ready


def test_robust_sigma_when_most_errors_are_equal() -> None:
    """Quantised or glitch-scored errors: the MAD is 0; the spread about the median is used."""
    r = np.array([0.0, 0.0, 0.0, 0.0, 1.0])
    assert robust_sigma(r) == pytest.approx(np.sqrt(1 / 5))
    assert error_statistics(r, 5 * robust_sigma(r)).outlier_fraction == 0.0
    assert robust_sigma(np.zeros(4)) == 0.0


@pytest.mark.parametrize(
    ("before", "after", "text", "relative"),
    [
        (0.2301, -0.2399, "worse by 4.3 %", 0.0426),  # the issue's: a sign flip is no gain
        (-0.2301, 0.2399, "worse by 4.3 %", 0.0426),
        (0.0197, 0.0020, "better by 90 %", -0.898),
        (-0.5, 0.1, "better by 80 %", -0.8),
        (0.1, 0.1, "unchanged", 0.0),
    ],
)
def test_change_compares_magnitudes(
    before: float, after: float, text: str, relative: float
) -> None:
    ch = change(before, after)
    assert ch.text == text and ch.relative == pytest.approx(relative, abs=1e-3)


def test_a_signed_metric_reads_by_its_magnitude() -> None:
    m = SecondaryMetric("known_rotation_error", "rad", 0.2301, -0.2399, signed=True)
    name, before, after, ch = metric_text(m, m.before)
    assert (before, after, ch) == ("0.2301", "0.2399", "worse by 4.3 %")
    assert name == "known_rotation_error magnitude (signed +0.2301 -> -0.2399)"


# --- in the report -----------------------------------------------------------------------------


def test_a_sign_flip_is_reported_as_the_worsening_it_is(tmp_path: Path) -> None:
    """A known total rotation 0.55 bias x T below the truth: under the declared (ideal) gyro the
    integral misses it by +0.45 b T, with the bias found by -0.55 b T: the signed error goes
    +0.45 -> -0.55 rad, smaller as a number, larger as an error."""
    bias, t0, t1 = 0.02, 5.0, 55.0
    probe = _gyro_bundle(tmp_path / "probe", 1)
    truth = np.loadtxt(probe / "truth_pose.csv", delimiter=",", skiprows=1)
    heading_at = np.interp([t0, t1], truth[:, 0], truth[:, 3])
    turned = float(heading_at[1] - heading_at[0])
    known = turned + 0.55 * bias * (t1 - t0)
    meta = {"reference": {"from_t": t0, "to_t": t1, "total_rotation_rad": known}}
    bundle = _gyro_bundle(tmp_path / "b", 1, bias, meta)
    out = tmp_path / "out"
    assert cli.run(_args(str(bundle), f"--out={out}")) == 0
    report = json.loads((out / "report.json").read_text())
    (e,) = (e for e in report["streams"] if e["metric"] == "known_rotation_error")
    assert e["signed"] is True
    assert e["before_signed"] == pytest.approx(0.45, abs=0.03)
    assert e["after_signed"] == pytest.approx(-0.55, abs=0.03)
    assert (e["before"], e["after"]) == (abs(e["before_signed"]), abs(e["after_signed"]))
    assert e["change"].startswith("worse by ") and e["relative_change"] > 0.1
    primary = report["streams"][0]
    assert primary["metric"] == "rms_rate_error" and primary["change"].startswith("better by ")
    md = (out / "report.md").read_text()
    row = next(line for line in md.splitlines() if "known_rotation_error" in line)
    assert "magnitude (signed +0.4" in row and "-> -0.5" in row and "worse by" in row


def test_heldout_errors_are_those_of_the_stream(tmp_path: Path) -> None:
    """heldout_errors in report.json are the statistics of the held-out residuals (gyro) and
    of the per-sample position errors (odometry), recomputed here with numpy; their RMS is the
    stream's metric."""
    bundle_dir = make_bundle(tmp_path / "b", 4)
    for f in ("compass.csv", "range.csv", "landmarks.csv", "landmark_map.csv"):
        (bundle_dir / f).unlink()
    bundle = load_bundle(bundle_dir)
    results = calibrate(bundle, declared_model(DECLARED, bundle.meta))
    report = report_json([Stage(1, str(bundle_dir), results)])
    first = {e["stream"]: e for e in reversed(report["streams"])}
    for res in results:
        p, sel = res.problem, res.selection
        errors = {"before": sel.before, "after": sel.after}
        got = first[p.name]["heldout_errors"]
        assert got["unit"] == p.unit
        for when, fit in errors.items():
            r = p.residuals(fit.insts, fit.x, "score")
            if p.name == "odometry":  # x errors then y errors: one norm per sample
                r = np.hypot(*r.reshape(2, -1))
            assert got["n"] == r.size > 100
            want = {
                "rms": np.sqrt(np.mean(r**2)),
                "median_abs": np.median(np.abs(r)),
                "p95_abs": np.percentile(np.abs(r), 95),
                "outlier_fraction": np.mean(np.abs(r - np.median(r)) > got["outlier_threshold"]),
            }
            for key, value in want.items():
                assert got[when][key] == pytest.approx(value, rel=1e-5), (p.name, when, key)
            if when == "after":
                mad = np.median(np.abs(r - np.median(r)))
                assert got["outlier_threshold"] == pytest.approx(5 * 1.4826 * mad, rel=1e-5)
        assert got["after"]["rms"] == pytest.approx(first[p.name]["after"], rel=1e-5)


# --- every stream named ------------------------------------------------------------------------


def test_every_stream_appears_with_what_it_lacks(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Gyro without a heading reference, an IR kind without true_range, landmarks without a map:
    each is in report.json, report.md and one log line, naming what is missing and how to add
    it; odometry and the sonar are calibrated."""
    b = make_bundle(tmp_path / "b", 5)
    (b / "compass.csv").unlink()
    (b / "landmark_map.csv").unlink()
    truth = np.loadtxt(b / "truth_pose.csv", delimiter=",", skiprows=1)
    _csv(b / "truth_pose.csv", "t,x,y", truth[:, 0], truth[:, 1], truth[:, 2])
    rng = np.loadtxt(b / "range.csv", delimiter=",", skiprows=1)
    rows = [(r[0], f"{r[0]:.10g},{r[1]:.0f},{r[2]:.10g},{r[3]:.10g},sonar") for r in rng]
    rows += [(t, f"{t:.10g},{s},{500 + 10 * s},,ir") for t in truth[::10, 0] for s in range(4)]
    rows.sort(key=lambda row: row[0])  # stable: one clock, rows in time order
    text = "\n".join(["t,sensor,measured,true_range,kind", *(r for _, r in rows)])
    (b / "range.csv").write_text(text + "\n", encoding="utf-8")
    (b / "beacons.csv").write_text("t,beacon,r\n0,1,2.5\n", encoding="utf-8")  # not read
    model = tmp_path / "model.toml"
    model.write_text(tomli_w.dumps(dict(DECLARED)), encoding="utf-8")
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="koala_bridge"):
        assert cli.run(_args(str(b), f"--config={model}", f"--out={out}")) == 0
    report = json.loads((out / "report.json").read_text())
    assert {e["stream"] for e in report["streams"]} == {"odometry", "range:sonar"}
    skipped = {e["stream"]: e for e in report["not_calibrated"]}
    assert set(skipped) == {
        "gyro",
        "range:ir",
        "landmark_range",
        "landmark_bearing",
        "beacons.csv",
    }
    assert skipped["beacons.csv"]["missing"] == "not a file of the bundle format: not read"
    assert "range.csv (t,sensor,measured,true_range" in skipped["beacons.csv"]["fix"]
    assert "truth_pose.csv has no theta column" in skipped["gyro"]["missing"]
    assert "no compass.csv" in skipped["gyro"]["missing"]
    assert skipped["gyro"]["fix"].startswith("add theta")
    assert skipped["range:ir"]["missing"].startswith("true_range is empty in every row")
    assert skipped["range:ir"]["fix"].startswith("add true_range (m) per row")
    assert "docs/bundle-format.md" in skipped["range:ir"]["fix"]
    for lm in ("landmark_range", "landmark_bearing"):
        assert skipped[lm]["missing"] == "no reference: the bundle has no landmark_map.csv"
    md = (out / "report.md").read_text()
    section = md[md.index("## Not calibrated") :]
    for name, e in skipped.items():
        assert f"**{name}**: {e['missing']}. To add it: {e['fix']}" in section
        assert f"| {name} | - | - | - | - | not calibrated |" in md
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    for name in skipped:
        assert sum(m.startswith(f"not calibrated: {name}: ") for m in warned) == 1, warned


def test_uwb_ranges_are_not_held_to_the_sonar_s_limits(tmp_path: Path) -> None:
    """Range beacons 3-8 m away, with a config that declares a sonar (default.toml: 0.25 to
    2.5 m): the sonar's limits are the sonar's. Once every UWB reading was dropped as a censored
    echo and the bundle got 'no stream has a reference'. The same readings as a sonar are
    dropped, and the report says why."""
    rng = np.random.default_rng(7)
    t = np.repeat(np.arange(0.0, 60.0, 0.1), 2)
    sensor = np.tile([0, 1], t.size // 2)
    true_r = 5.5 + 2.5 * np.sin(2 * np.pi * t / 13 + sensor)
    measured = true_r + 0.1 + rng.normal(0, 0.03, t.size)  # a 10 cm bias the model lacks
    b = tmp_path / "uwb"
    b.mkdir()
    rows = [
        f"{a:.10g},{s},{m:.10g},{r:.10g},{kind}"
        for kind in ("uwb", "sonar")
        for a, s, m, r in zip(t, sensor, measured, true_r, strict=True)
    ]
    rows.sort(key=lambda row: float(row.split(",")[0]))
    (b / "range.csv").write_text(
        "t,sensor,measured,true_range,kind\n" + "\n".join(rows) + "\n", encoding="utf-8"
    )
    (b / "meta.json").write_text('{"units": {"range.measured": "m"}}', encoding="utf-8")
    out = tmp_path / "out"
    assert cli.run(_args(str(b), f"--config={DEFAULT_TOML}", f"--out={out}")) == 0
    report = json.loads((out / "report.json").read_text())
    (uwb,) = report["streams"]
    assert uwb["stream"] == "range:uwb"
    (bias,) = (e for e in uwb["effects"] if e["name"] == "bias")
    assert bias["params"]["bias"] == pytest.approx(0.1, abs=0.01) and bias["written"]
    (sonar,) = report["not_calibrated"]
    assert sonar["stream"] == "range:sonar"
    assert f"0 usable rows of {t.size}" in sonar["missing"]
    assert "beyond the declared sonar's critical incidence angle" in sonar["missing"]
    assert "min_range_m..max_range_m" in sonar["fix"] and "a kind column (e.g. uwb)" in sonar["fix"]


def test_a_still_ir_recording_says_what_it_lacks(tmp_path: Path) -> None:
    """Each IR sensor saw one distance (the robot stood still) and no curve is declared: a curve
    fitted to those distances explains every reading. The stream is named with why, and with
    nothing else in the input the one error line says it."""
    rng = np.random.default_rng(2)
    t = np.repeat(np.arange(0.0, 20.0, 0.1), 8)
    sensor = np.tile(np.arange(8), t.size // 8)
    true_r = 0.02 + 0.01 * sensor
    counts = np.rint(900 * np.exp(-true_r / 0.03) + rng.normal(0, 5, t.size))
    b = tmp_path / "still"
    b.mkdir()
    _csv(b / "range.csv", "t,sensor,measured,true_range", t, sensor, counts, true_r)
    (b / "meta.json").write_text('{"units": {"range.measured": "counts"}}', encoding="utf-8")
    bundle = load_bundle(b)
    skipped: list[SkippedStream] = []
    assert calibrate(bundle, declared_model({}, bundle.meta), skipped=skipped) == []
    (s,) = skipped
    assert s.stream == "range" and "true_range does not vary for any sensor" in s.missing
    assert "several distances per sensor" in s.fix
    with pytest.raises(BundleError, match=r"no stream can be calibrated: range: true_range does"):
        cli.run(_args(str(b), f"--out={tmp_path / 'out'}"))


def test_data_under_another_file_name_is_named(tmp_path: Path) -> None:
    """Range beacons in uwb.csv and odometry in odom.csv, beside truth_pose.csv: neither is a
    file of the format. The one error line names both and the files they should be."""
    b = tmp_path / "b"
    b.mkdir()
    t = np.arange(0.0, 10.0, 0.1)
    _csv(b / "truth_pose.csv", "t,x,y", t, t * 0.1, t * 0)
    _csv(b / "uwb.csv", "t,anchor,range", t, t * 0 + 1, 3 + t * 0.1)
    _csv(b / "odom.csv", "t,left_ticks,right_ticks", t, t * 100, t * 100)
    with pytest.raises(BundleError) as e:
        cli.run(_args(str(b), f"--out={tmp_path / 'out'}"))
    line = str(e.value)
    assert "\n" not in line and "no stream can be calibrated" in line
    assert (
        "odom.csv: not a file of the bundle format: not read: if it holds that stream, name it "
        "odometry.csv with the columns t" in line
    )
    assert "uwb.csv: not a file of the bundle format" in line and "kind column such as uwb" in line


# --- never write an uncertain effect -----------------------------------------------------------


def _forced_bias(tmp_path: Path, seed: int, bias: float) -> StreamResult:
    """The gyro stream with a ``bias`` put into its model whatever the selection says, as an
    effect that passed on the fit part and whose size the data barely tell."""
    bundle = load_bundle(_gyro_bundle(tmp_path / f"b{seed}", seed, bias))
    problem = build_gyro(bundle, declared_model(DECLARED, bundle.meta))
    assert problem is not None
    before = fit_model(problem, [], problem.nuisance_x0())
    (inst,) = get_effect("bias").propose(problem)
    after = fit_model(problem, [inst], problem.initial_vector([inst], before.x, []))
    sel = Selection(problem, before, after, [(inst, judge(before, after, 1, 1, 0.0))])
    return StreamResult(
        problem,
        sel,
        problem.metric_value([], before.x, "score"),
        problem.metric_value([inst], after.x, "score"),
    )


def _bias_and_se(res: StreamResult) -> tuple[float, float]:
    after = res.selection.after
    return float(after.x[0]), float(parameter_se(res.problem, after)[0])


def test_an_effect_within_its_uncertainty_is_not_written(tmp_path: Path) -> None:
    """No bias in the data: the fitted one is smaller than its standard error (checked here, at
    this seed). It is neither in the written keys nor carried; the report says why. A bias of
    20 standard errors is written."""
    res = _forced_bias(tmp_path, 4, 0.0)
    value, se = _bias_and_se(res)
    assert abs(value) < se  # the seed gives the case the brief names: SE larger than the size
    (reason,) = res.not_written()
    assert reason is not None and reason.startswith("uncertainty larger than the effect")
    assert "sensors.gyro.bias_rad_s" not in found_keys([res])
    stage = Stage(1, "b4", [res])
    (entry,) = (e for e in report_json([stage])["streams"] if e["metric"] == "rms_rate_error")
    (effect,) = entry["effects"]
    assert effect["written"] is False
    assert effect["not_written"].startswith("uncertainty larger than the effect")
    md = report_markdown([stage], "", plots=False)
    assert "| **not written**: uncertainty larger than the effect" in md
    assert "bias (not written)" in md
    # the written model is the declared one here (its only effect left out): its held-out
    # metric is *before*, and the report gives it beside *after*
    assert res.after_written() == pytest.approx(res.before)
    assert entry["after_written"] == pytest.approx(res.before, rel=1e-5)
    assert "(written model: " in md

    strong = _forced_bias(tmp_path / "strong", 4, 20 * se)
    assert strong.not_written() == [None]
    assert strong.after_written() is None
    assert found_keys([strong])["sensors.gyro.bias_rad_s"] == pytest.approx(20 * se, rel=0.1)


def test_the_written_model_leaves_out_an_effect_written_as_a_comment(tmp_path: Path) -> None:
    # A gyro's time offset has no simulator key: --write-config puts it in a comment, so the
    # model a reader simulates lacks it, and the written model's error says what that leaves.
    bundle = load_bundle(make_bundle(tmp_path / "b", 5, Injected(gyro_time_offset=0.05)))
    (res,) = (r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
              if r.problem.name == "gyro")
    assert [i.name for i in res.effects] == ["time_offset"]
    assert res.not_written() == [None]               # certain: written, as a comment
    md = report_markdown([Stage(1, "b", [res])], "", plots=False)
    assert "written as a comment: the simulator has no key for it" in md
    # the simulated model is the declared one: its held-out error is *before*, not *after*
    assert res.after_written() == pytest.approx(res.before)
    assert res.after < 0.5 * res.before


def test_an_effect_of_1_5_standard_errors_is_not_written(tmp_path: Path) -> None:
    """The issue's wheel slip proposed ticks_per_metre 22 222 -> 70 968 with SE 32 500: 1.5 SE,
    larger than its SE and still no effect to write. A bias fitted at 1.5 SE (this seed) is
    reported, not written."""
    _, se = _bias_and_se(_forced_bias(tmp_path, 4, 0.0))
    res = _forced_bias(tmp_path / "weak", 4, 1.5 * se)
    value, se = _bias_and_se(res)
    assert se < abs(value) < WRITE_Z * se  # larger than its SE, inside the 99 % interval
    assert res.not_written()[0] is not None
    assert "sensors.gyro.bias_rad_s" not in found_keys([res])


def test_an_effect_without_a_simulator_key_is_written_as_a_comment(tmp_path: Path) -> None:
    """A gyro latency has no key in the simulator's config: --write-config puts it in the
    trailing comment block and the model change's diff shows none, so the report's cell says
    "written as a comment", not "written" (which read as a contradiction of the diff)."""
    from koala_bridge.calibration.pipeline import Options
    from koala_bridge.calibration.report import write_report
    from koala_bridge.calibration.stages import calibrate_stages
    from koala_bridge.calibration.synthetic import CASES

    d = make_bundle(tmp_path / "b", seed=1000, inj=CASES["time_offset"].inject)
    stages, _ = calibrate_stages([d], DECLARED, Options(), tmp_path / "tmp")
    (gyro,) = [r for r in stages[-1].results if r.problem.name == "gyro"]
    assert [i.name for i in gyro.effects] == ["time_offset"]
    write_report(tmp_path / "out", stages, "", plots=False)
    md = (tmp_path / "out" / "report.md").read_text()
    (row,) = [line for line in md.splitlines() if line.startswith("| time_offset | {")]
    assert row.endswith("| written as a comment: the simulator has no key for it |")


def _forced_scale(tmp_path: Path, inj: Injected, names: list[str]):  # noqa: ANN202
    """A gyro result with the effects ``names`` (time_offset first, scale among them) fitted
    together, then the scale set to a gain 20 % high and kept: ``(problem, res, x, insts)``."""
    from dataclasses import replace

    from koala_bridge.calibration.pipeline import candidates_for

    bundle = load_bundle(make_bundle(tmp_path / "b", 5, inj))
    (problem,) = (r.problem for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
                  if r.problem.name == "gyro")
    cands = {c.name: c for c in candidates_for(problem)}
    insts = [cands[n] for n in names]
    before = fit_model(problem, [], problem.nuisance_x0())
    fitted = fit_model(problem, insts, problem.initial_vector(insts, before.x, []))
    x = fitted.x.copy()
    x[len(problem.nuisance_x0()) + cands["time_offset"].n_free] = 0.2   # the scale, kept
    after = replace(fitted, x=x)
    trial = judge(before, after, 1, 1, 0.0)
    res = StreamResult(problem, Selection(problem, before, after, [(i, trial) for i in insts]),
                       problem.metric_value([], before.x, "score"),
                       problem.metric_value(after.insts, after.x, "score"))
    return problem, res, x, insts


def test_a_simulated_effect_that_helps_only_beside_a_comment_is_not_written(
    tmp_path: Path,
) -> None:
    # A gyro's scale fitted together with its time offset (which the simulator cannot hold)
    # can leave the simulated config worse than the declared one: written alone, at its
    # value, it must beat the declared model on held-out data, or it is not written.
    problem, res, x, (tau, scale) = _forced_scale(
        tmp_path, Injected(gyro_time_offset=0.05), ["time_offset", "scale"])
    alone = problem.metric_value([scale], problem.initial_vector([scale], x, [tau, scale]),
                                 "score")
    assert alone > res.before                   # the scale alone, at its value, is worse
    assert res.not_written()[0] is None         # the time offset: written, as a comment
    reason = res.not_written()[1]
    assert reason is not None and reason.startswith("alone it does not improve")
    assert "without time_offset (written only as a comment)" in reason
    assert "sensors.gyro.scale_factor_error" not in found_keys([res])
    assert res.after_written() == pytest.approx(res.before)    # nothing simulated is written
    (entry,) = (e for e in report_json([Stage(1, "b", [res])])["streams"]
                if e["metric"] == "rms_rate_error")
    assert entry["effects"][0]["written_as"] == "comment"
    assert entry["effects"][1]["written"] is False


def test_the_simulated_effect_that_spoils_the_written_model_is_left_out_and_the_rest_written(
    tmp_path: Path,
) -> None:
    # The scale above beside a real bias: written together (without the time offset) they lose
    # to the declared model; left out in turn, the scale goes (its removal leaves the better
    # model) and the bias, which beats the declared model on its own, is written.
    problem, res, x, insts = _forced_scale(
        tmp_path, Injected(gyro_time_offset=0.05, gyro_bias=0.05),
        ["time_offset", "scale", "bias"])
    _, scale, bias = insts

    def alone(keep: list) -> float:
        return problem.metric_value(keep, problem.initial_vector(keep, x, insts), "score")

    assert alone([scale, bias]) > res.before           # both, as written, lose
    assert alone([bias]) < res.before < alone([scale])  # the bias alone wins, the scale loses
    tau_why, scale_why, bias_why = res.not_written()
    assert tau_why is None and bias_why is None
    assert scale_why is not None
    assert scale_why.startswith("the written model does not beat the declared one with it")
    keys = found_keys([res])
    assert "sensors.gyro.bias_rad_s" in keys and "sensors.gyro.scale_factor_error" not in keys
    assert res.after_written() == pytest.approx(alone([bias]))


def test_every_level_of_a_per_sensor_offset_is_reported(tmp_path: Path) -> None:
    """The offsets of ``offset_per`` sum to 0 over the fit part's levels, so the last is no
    free parameter; it is still that level's offset: a new user found the fourth UWB anchor's
    only in the written config's comment. report.json gives it, marked derived."""
    offsets = (0.05, -0.03, 0.02, -0.04)
    bundle = load_bundle(make_bundle(tmp_path / "b", seed=4,
                                     inj=Injected(sonar_per_sensor=offsets), duration_s=120.0))
    results = [r for r in calibrate(bundle, declared_model(DECLARED, bundle.meta))
               if r.problem.name == "range"]
    report = report_json([Stage(1, "b", results)])
    (entry,) = (e for s in report["streams"] for e in s["effects"]
                if e["name"] == "offset_per:sensor")
    params = entry["params"]
    assert set(params) == {"offset_0", "offset_1", "offset_2", "offset_3"}
    assert entry["derived"].keys() == {"offset_3"}
    assert sum(params.values()) == pytest.approx(0.0, abs=1e-5)
    # the offsets about their mean, the common part being bias's: 1 cm of noise over some 1400
    # fit readings per sensor is an SE of 0.27 mm, the bound 7 of them
    mean = float(np.mean(offsets))
    for k, o in enumerate(offsets):
        assert params[f"offset_{k}"] == pytest.approx(o - mean, abs=0.002)
