"""Real bundles (copied from shared/data/real into tests/data/real, see PROVENANCE.md).

Each test checks that the report names the effect the bundle's README describes and lowers the
held-out error accordingly. The thresholds come from the README's held-out figures, not from
the tool's own output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from koala_bridge.calibration.bundle import load_bundle
from koala_bridge.calibration.model import declared_model
from koala_bridge.calibration.pipeline import StreamResult, calibrate

DATA = Path(__file__).parents[1] / "data" / "real"


def _calibrate(name: str) -> dict[str, StreamResult]:
    bundle = load_bundle(DATA / name)
    return {r.problem.name: r for r in calibrate(bundle, declared_model({}, bundle.meta))}


def _params(res: StreamResult) -> dict[str, dict[str, float]]:
    return {i.name: p for i, (p, _) in zip(res.effects, res.effect_params(), strict=True)}


def test_lego_brenner_tick_scale_and_wheel_base() -> None:
    odo = _calibrate("lego_brenner")["odometry"]
    names = [i.name for i in odo.effects]
    assert {"wheel_base", "tick_scale"} <= set(names)
    assert odo.before > 0.4  # nominal geometry: of the order of the README's 0.7 m
    assert odo.after <= odo.before / 5
    p = _params(odo)
    # README: ~178 mm wheel base (+19 %), ~0.360 mm per tick (2778 ticks/m, +3 %).
    assert 0.165 < p["wheel_base"]["wheel_base_m"] < 0.195
    assert 2650 < p["tick_scale"]["ticks_per_metre"] < 2830


def test_mpu6050_gyro_static_bias() -> None:
    gyro = _calibrate("mpu6050_gyro_static")["gyro"]
    assert [i.name for i in gyro.effects][0] == "bias"
    assert _params(gyro)["bias"]["bias"] == pytest.approx(0.0196, abs=3e-4)
    heading = gyro.secondary[0]
    assert heading.before == pytest.approx(0.196, rel=0.05)  # README: 0.196 rad per 10 s
    assert heading.after < 0.01


def test_mpu6050_turns_compass_hard_iron() -> None:
    res = _calibrate("mpu6050_turns")
    compass = res["compass"]
    assert [i.name for i in compass.effects][0] == "hard_iron"
    p = _params(compass)["hard_iron"]
    # README: about (0.01, -0.21) gauss in the horizontal plane.
    assert np.hypot(p["dh_x"] - 0.01, p["dh_y"] + 0.21) < 0.03
    assert compass.after < compass.before / 2
    assert "gyro" in res  # scored against the calibrated compass heading


def test_hmc5883l_sphere_hard_and_soft_iron() -> None:
    compass = _calibrate("hmc5883l_sphere")["compass"]
    assert {"hard_iron", "soft_iron"} <= {i.name for i in compass.effects}
    assert compass.before == pytest.approx(13.6, abs=0.2)  # README: 13.6 % spread
    assert compass.after < 1.0  # README: 0.7 % held-out
    h = _params(compass)["hard_iron"]
    assert np.allclose([h["dh_x"], h["dh_y"], h["dh_z"]], [-0.009, -0.107, 0.020], atol=0.01)


def test_khepera2_ir_per_sensor_offset() -> None:
    ir = _calibrate("khepera2_ir")["range"]
    assert ir.effects[0].name == "offset_per:sensor"
    assert 35 < ir.before < 55  # README: one shared curve 46 counts RMS held-out
    assert ir.after < 25  # README: shared curve + per-sensor offset 19 counts RMS


def test_mpu6050_turns_staged_after_the_still_recording(tmp_path: Path) -> None:
    """The turns alone cannot tell the gyro's bias (the compass heading's hand-tilt error is
    as large, and the known total is one number). Staged, still recording first, the bias it
    finds is carried into the turns' model: the report names it there (with the stage that
    found it) beside the compass's hard iron, and the held-out errors fall as the README says.
    """
    from koala_bridge.calibration.pipeline import Options
    from koala_bridge.calibration.stages import calibrate_stages

    stages, config = calibrate_stages(
        [DATA / "mpu6050_gyro_static", DATA / "mpu6050_turns"], {}, Options(), tmp_path
    )
    assert config["sensors"]["gyro"]["bias_rad_s"] == pytest.approx(0.0196, abs=3e-4)
    turns = stages[1]
    res = {r.problem.name: r for r in turns.results}
    (carried,) = turns.carried["sensors.gyro"]
    assert (carried.name, carried.stage) == ("bias", 1)
    gyro, compass = res["gyro"], res["compass"]
    heading = turns.declared_before[("gyro", gyro.problem.metric)]
    assert gyro.after < 0.8 * heading  # 0.142 -> 0.108 rad per 10 s window
    # The known +4 pi: README 733 deg integrated as ideal (+13 deg), 706 with the bias (-14 deg).
    (rotation,) = (m for m in gyro.secondary if m.metric == "known_rotation_error")
    assert np.degrees(turns.declared_before[("gyro", "known_rotation_error")]) == pytest.approx(
        13.0, abs=1.0
    )
    assert np.degrees(rotation.after) == pytest.approx(-14.0, abs=1.0)
    # README: raw compass heading 0.74 rad RMS off the bias-corrected gyro heading, 0.19 after
    # a 2-D hard-iron fit (held-out).
    assert [i.name for i in compass.effects][0] == "hard_iron"
    (vs_gyro,) = (m for m in compass.secondary if m.metric == "heading_error_vs_declared_gyro_rms")
    assert 0.6 < vs_gyro.before < 0.9
    assert vs_gyro.after < 0.2
