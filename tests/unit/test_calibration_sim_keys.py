"""The simulator honours the keys ``koala-bridge calibrate --write-config`` writes.

``[sensors.gyro] bias_rad_s``, ``[robot] wheel_diameter_ratio`` and
``[sensors.ir] per_sensor_offset_counts`` (docs/calibration.md, "What the simulator reproduces"),
each checked exactly with every noise source of that sensor switched off.
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim.simulator import Simulator
from koala_bridge.sim.types import WheelCommand

CONFIG = Path(__file__).parents[2] / "config"


def _ideal() -> dict[str, Any]:
    with (CONFIG / "ideal.toml").open("rb") as fh:
        return tomllib.load(fh)


def test_gyro_fixed_bias_is_added_to_every_sample() -> None:
    cfg = _ideal()
    g = cfg["sensors"]["gyro"]
    g.update(
        ideal=False,
        gyroscope_noise_density=0.0,
        gyroscope_random_walk=0.0,
        turn_on_bias_sigma=0.0,
        scale_noise=0.0,
        scale_factor_error=0.02,
        bias_rad_s=0.0123,
    )
    sim = Simulator(cfg)
    sim.reset(3)
    for _ in range(50):
        r = sim.step(WheelCommand(-0.1, 0.1))
        assert r.gyro is not None
        assert r.gyro.yaw_rate == pytest.approx(1.02 * r.gyro.truth_yaw_rate + 0.0123, abs=1e-12)


def test_wheel_diameter_ratio_moves_the_pose_not_the_ticks() -> None:
    cfg = _ideal()
    rho = 1.02
    cfg["robot"]["wheel_diameter_ratio"] = rho
    sim = Simulator(cfg)
    sim.reset(1)
    v, n = 0.2, 100
    for _ in range(n):
        r = sim.step(WheelCommand(v, v))
    assert r.odometry is not None
    tpm = cfg["robot"]["ticks_per_metre"]
    # The encoders count the commanded rotation: equal on both wheels.
    assert r.odometry.left_ticks == r.odometry.right_ticks == math.floor(v * n * 0.01 * tpm + 0.5)
    # The larger left wheel travels further: the robot turns right at (v_r - v_l) / b.
    vl, vr = v * 2 * rho / (1 + rho), v * 2 / (1 + rho)
    expected = (vr - vl) / cfg["robot"]["wheel_base_m"] * n * 0.01
    assert r.pose.theta == pytest.approx(expected, rel=1e-9)


def test_ir_per_sensor_offsets_are_added_to_the_counts() -> None:
    cfg = _ideal()
    ir = cfg["sensors"]["ir"]
    offsets = [float(i) - 7.0 for i in range(16)]
    ir.update(
        ideal=False,
        distance_error=[[0.0, 0.0], [1.0, 0.0]],
        count_noise_sigma=0.0,
        ambient_noise_counts=0.0,
        ambient_saturation=0.0,
        per_sensor_offset_counts=offsets,
    )
    sim = Simulator(cfg)
    r = sim.reset(1)
    assert r.ir is not None
    counts = np.asarray(r.ir.counts, dtype=float)
    expected = np.clip(np.asarray(r.ir.truth_counts, dtype=float) + offsets, 0, 1023)
    assert np.all(np.abs(counts - expected) <= 0.5)
    bad = copy.deepcopy(cfg)
    bad["sensors"]["ir"]["per_sensor_offset_counts"] = [1.0, 2.0]
    with pytest.raises(ConfigError, match="per_sensor_offset_counts"):
        Simulator(bad)
