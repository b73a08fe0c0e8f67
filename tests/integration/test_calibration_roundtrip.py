"""Closing the loop (issue 6): the written config, simulated, reproduces the measured residual.

1. A real bundle (the still MPU6050 gyro) is calibrated against ``config/ideal.toml``; the
   config written with ``--write-noise`` is simulated (robot still) and the simulated recording
   calibrated the same way: its bias matches the real one within 3 combined standard errors and
   its residual variance the real one within the F interval of the two sample sizes.
2. The simulator with undeclared effects plays the measured robot (compass hard and soft iron,
   tick size, wheel base, IR per-sensor offsets): calibrated against ``config/default.toml``,
   the tool names exactly those effects; the written config, simulated with another seed and
   calibrated against itself, adds nothing, and each stream's residual RMS matches the first
   calibration's *after* within the F interval of the two held-out parts.
3. MCAP round trip: a recording of the simulator under ``config/default.toml`` calibrated
   directly (``.mcap`` input, through ``recording.export.export_bundle``) against that config
   adds no effect; with a gyro bias injected into the exported bundle, ``bias`` is found.

Bounds are at a two-sided false-alarm probability of 1e-3 per check.
"""

from __future__ import annotations

import copy
import csv
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _sim_inject import STREAMS
from koala_bridge.calibration.bundle import load_bundle, load_input
from koala_bridge.calibration.config_update import found_keys, noise_keys, updated_config
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate
from koala_bridge.calibration.selection import prewhiten
from koala_bridge.recording.export import export_bundle
from koala_bridge.tools.sim_recording import record_simulator
from scipy import stats

ROOT = Path(__file__).parents[2]
DATA = ROOT / "tests" / "data" / "real"
ALPHA = 1e-3


def _load(name: str) -> dict[str, Any]:
    with (ROOT / "config" / name).open("rb") as fh:
        return tomllib.load(fh)


def _by_name(results: list[StreamResult]) -> dict[str, StreamResult]:
    return {r.problem.name: r for r in results}


def _params(res: StreamResult) -> dict[str, dict[str, float]]:
    return {i.name: p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)}


def _calibrate_dir(path: Path, config: dict[str, Any]) -> dict[str, StreamResult]:
    bundle = load_bundle(path)
    return _by_name(calibrate(bundle, declared_model(config, bundle.meta)))


def _simulate(
    config: dict[str, Any], tmp: Path, name: str, seed: int, duration_s: float, **kw: Any
) -> Path:
    mcap = record_simulator(config, tmp / f"{name}.mcap", duration_s, seed=seed, **kw)
    return export_bundle(mcap, tmp / name)


def _score_residual(res: StreamResult) -> np.ndarray:
    sel = res.selection
    return res.problem.residuals(sel.after.insts, sel.after.x, "score")


def _f_interval(n1: float, n2: float) -> tuple[float, float]:
    """Two-sided interval of s1^2 / s2^2 for equal variances (F with n1, n2 dof)."""
    return stats.f.ppf(ALPHA / 2, n1, n2), stats.f.ppf(1 - ALPHA / 2, n1, n2)


def _dof(res: StreamResult) -> float:
    counts = res.problem.independent_count("score")
    if counts is not None:
        return float(counts)
    return float(prewhiten(_score_residual(res), res.selection.rho).size)


def _same_variance(a: StreamResult, b: StreamResult) -> tuple[float, tuple[float, float]]:
    va, vb = np.mean(_score_residual(a) ** 2), np.mean(_score_residual(b) ** 2)
    return float(va / vb), _f_interval(_dof(a), _dof(b))


def test_real_gyro_bias_and_noise_reproduced_by_the_simulator(tmp_path: Path) -> None:
    model = _load("ideal.toml")
    bundle = load_bundle(DATA / "mpu6050_gyro_static")
    real = _by_name(calibrate(bundle, declared_model(model, bundle.meta)))["gyro"]
    keys = {**found_keys([real]), **noise_keys([real])}
    written = updated_config(model, keys)
    gyro = written["sensors"]["gyro"]
    assert gyro["ideal"] is False
    assert gyro["bias_rad_s"] == pytest.approx(0.0196, abs=3e-4)
    # The unmeasured terms of a model switched on are absent, not ideal.toml's assumed values.
    assert gyro["turn_on_bias_sigma"] == gyro["gyroscope_random_walk"] == 0.0

    # The test copy keeps 1 sample in 10 (tests/data/real/PROVENANCE.md): ~10 Hz. A sample's
    # noise is the sensor's per-sample sigma whatever is dropped between samples, and the
    # written density is that sigma at the bundle's sample interval (Kalibr), so the simulator
    # reproduces it at the bundle's rate.
    written["sensors"]["gyro"]["rate_hz"] = 10
    sim_dir = _simulate(
        written, tmp_path, "still", 7, 600.0, command=lambda t: (0.0, 0.0), pose_rate_hz=10.0
    )
    sim = _calibrate_dir(sim_dir, model)["gyro"]
    assert [i.name for i in sim.effects] == ["bias"]
    b_real, se_real = real.effect_params()[0][0]["bias"], real.effect_params()[0][1]["bias"]
    b_sim, se_sim = sim.effect_params()[0][0]["bias"], sim.effect_params()[0][1]["bias"]
    assert abs(b_sim - b_real) <= 3 * np.hypot(se_real, se_sim)
    ratio, (lo, hi) = _same_variance(sim, real)
    assert lo <= ratio <= hi, (ratio, lo, hi)


#: The robot the simulator plays: undeclared effects on top of config/default.toml.
HIDDEN = {
    "hard_iron_uT": [10.0, -8.0, 1.0],  # declared [4.0, -2.5, 1.0]
    "soft_iron": [[1.10, 0.04, 0.0], [0.04, 0.93, 0.0], [0.0, 0.0, 1.0]],
    "ticks_per_metre": 22222.222 * 1.08,
    "wheel_base_m": 0.285 * 1.12,
    "ir_offsets": [
        5.0,
        10.0,
        30.0,
        12.0,
        0.0,
        8.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        20.0,
        25.0,
        0.0,
        15.0,
        4.0,
    ],
}


def _hidden_robot(base: dict[str, Any]) -> dict[str, Any]:
    cfg = copy.deepcopy(base)
    cfg["sensors"]["compass"]["hard_iron_uT"] = HIDDEN["hard_iron_uT"]
    cfg["sensors"]["compass"]["soft_iron"] = HIDDEN["soft_iron"]
    cfg["robot"]["ticks_per_metre"] = HIDDEN["ticks_per_metre"]
    cfg["robot"]["wheel_base_m"] = HIDDEN["wheel_base_m"]
    cfg["sensors"]["ir"]["per_sensor_offset_counts"] = HIDDEN["ir_offsets"]
    return cfg


def test_written_config_reproduces_the_residual_of_the_robot_it_was_fitted_to(
    tmp_path: Path,
) -> None:
    default = _load("default.toml")
    measured_dir = _simulate(_hidden_robot(default), tmp_path, "robot", 11, 60.0)
    # A recording's meta.json declares the recorded robot's geometry, which would win over the
    # config (bundle precedence); the robot played here does not know its own.
    meta = json.loads((measured_dir / "meta.json").read_text())
    meta["robot"] = {k: v for k, v in meta["robot"].items() if k == "start_pose"}
    (measured_dir / "meta.json").write_text(json.dumps(meta))
    first = _calibrate_dir(measured_dir, default)
    found = {name: {i.name for i in r.effects} for name, r in first.items()}
    assert found["compass"] == {"hard_iron", "soft_iron"}
    assert found["odometry"] == {"tick_scale", "wheel_base"}
    # Per-sensor offsets relative to their mean, and the mean of the sensors that saw a wall.
    assert found["range:ir"] == {"offset_per:sensor", "bias"}
    assert all(not v for k, v in found.items() if k not in ("compass", "odometry", "range:ir"))
    compass = _params(first["compass"])["hard_iron"]
    assert compass["dh_x"] == pytest.approx(6.0, abs=0.6)  # 10 - 4 declared
    assert compass["dh_y"] == pytest.approx(-5.5, abs=0.6)
    odo = _params(first["odometry"])
    assert odo["tick_scale"]["ticks_per_metre"] == pytest.approx(
        HIDDEN["ticks_per_metre"], rel=0.01
    )
    assert odo["wheel_base"]["wheel_base_m"] == pytest.approx(HIDDEN["wheel_base_m"], rel=0.01)

    written = updated_config(default, found_keys(list(first.values())))
    ir_written = np.asarray(written["sensors"]["ir"]["per_sensor_offset_counts"])
    assert ir_written.size == 16
    # Every sensor that saw a wall gets its own offset (count noise 2, hundreds of readings).
    (per_sensor,) = (i for i in first["range:ir"].effects if i.name == "offset_per:sensor")
    seen = per_sensor.data["levels"].astype(int)
    assert len(seen) >= 4 and {2, 3} <= set(seen), seen
    assert np.allclose(ir_written[seen], np.asarray(HIDDEN["ir_offsets"])[seen], atol=6.0), (
        ir_written[seen]
    )

    again_dir = _simulate(written, tmp_path, "again", 12, 60.0)
    second = _calibrate_dir(again_dir, written)
    assert {k: [i.name for i in r.effects] for k, r in second.items() if r.effects} == {}
    for name in ("compass", "odometry", "range:ir", "gyro"):
        ratio, (lo, hi) = _same_variance(second[name], first[name])
        assert lo <= ratio <= hi, (name, ratio, lo, hi)


def _add_to_column(path: Path, column: str, value: float) -> None:
    rows = list(csv.reader(path.open()))
    j = rows[0].index(column)
    for row in rows[1:]:
        if row[j]:
            row[j] = repr(float(row[j]) + value)
    with path.open("w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)


def test_mcap_of_the_simulator_is_white_against_its_own_config(tmp_path: Path) -> None:
    default = _load("default.toml")
    mcap = record_simulator(default, tmp_path / "run.mcap", 30.0, seed=5)
    bundle = load_input(mcap, tmp_path / "work")
    assert {"gyro", "compass", "odometry", "range", "landmarks", "truth_pose"} <= set(bundle.tables)
    results = calibrate(bundle, declared_model(default, bundle.meta))
    assert {r.problem.name for r in results} >= STREAMS
    assert {r.problem.name: [i.name for i in r.effects] for r in results if r.effects} == {}

    exported = export_bundle(mcap, tmp_path / "injected")
    _add_to_column(exported / "gyro.csv", "yaw_rate", 0.02)
    gyro = _calibrate_dir(exported, default)["gyro"]
    assert [i.name for i in gyro.effects] == ["bias"]
    # The turn-on bias of this run is part of the declared model: bias = 0.02 + its draw.
    assert _params(gyro)["bias"]["bias"] == pytest.approx(0.02, abs=4 * 0.002)
