"""Determinism, RNG streams, the error-model seam and typed config errors."""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import numpy as np
import pytest
from test_sim_support import default_config

from sim.config import load_sim_config
from sim.schema import ConfigError
from sim.simulator import RNG_STREAMS, Simulator
from sim.types import GyroReading, Readings, WheelCommand


def _flatten(r: Readings) -> list[Any]:
    out: list[Any] = [r.t, r.pose, r.wheel_speeds, r.collided]
    for name in ("ir", "sonar", "odometry", "gyro", "compass", "camera"):
        v = getattr(r, name)
        if v is None:
            out.append(None)
            continue
        for f in vars(v).values():
            out.append(f.tobytes() if isinstance(f, np.ndarray) else f)
    return out


def _run(cfg: dict, seed: int, n: int = 400, **kw: Any) -> list[list[Any]]:
    sim = Simulator(cfg, **kw)
    rs = [_flatten(sim.reset(seed))]
    rng = np.random.default_rng(99)            # the command sequence, fixed
    for _ in range(n):
        rs.append(_flatten(sim.step(WheelCommand(*rng.uniform(-0.2, 0.4, 2)))))
    return rs


def test_same_seed_is_bit_identical() -> None:
    cfg = default_config()
    assert _run(cfg, 5) == _run(cfg, 5)


def test_reset_restarts_the_run() -> None:
    sim = Simulator(default_config())
    a = [_flatten(sim.reset(3))] + [_flatten(sim.step(WheelCommand(0.1, 0.2))) for _ in range(50)]
    b = [_flatten(sim.reset(3))] + [_flatten(sim.step(WheelCommand(0.1, 0.2))) for _ in range(50)]
    assert a == b


def test_ideal_sensors_do_not_depend_on_the_seed() -> None:
    cfg = default_config()
    assert _run(cfg, 1, 200) == _run(cfg, 2, 200)


class _NoisyGyro:
    """A stand-in error model: adds N(0, sigma) from the gyro's own stream."""

    def __init__(self, sigma: float, rng: np.random.Generator) -> None:
        self.sigma = sigma
        self.bias = float(rng.normal())            # turn-on state drawn at reset

    def measure(self, truth: Any, rng: np.random.Generator) -> GyroReading:
        return GyroReading(truth.yaw_rate + self.bias + self.sigma * rng.normal(), truth.yaw_rate)


def _noisy_cfg() -> dict:
    cfg = copy.deepcopy(default_config())
    cfg["sensors"]["gyro"]["ideal"] = False
    return cfg


FACTORIES = {"gyro": lambda params, rng: _NoisyGyro(0.01, rng)}


def test_error_model_seam_and_seed_dependence() -> None:
    cfg = _noisy_cfg()
    a = Simulator(cfg, error_models=FACTORIES)
    b = Simulator(cfg, error_models=FACTORIES)
    ra, rb, rc = a.reset(1), b.reset(1), b.reset(2)
    assert ra.gyro.yaw_rate == rb.gyro.yaw_rate != rc.gyro.yaw_rate
    assert ra.gyro.truth_yaw_rate == rc.gyro.truth_yaw_rate == 0.0
    # Different seeds differ only where noise exists: every other reading is identical.
    for _ in range(100):
        ra, rc = a.step(WheelCommand(0.1, 0.3)), b.step(WheelCommand(0.1, 0.3))
        assert ra.gyro.yaw_rate != rc.gyro.yaw_rate
        assert ra.gyro.truth_yaw_rate == rc.gyro.truth_yaw_rate
        ga, gc = _flatten(ra), _flatten(rc)
        assert ga[:4] == gc[:4]
        def not_float(xs: list[Any]) -> list[Any]:
            return [x for x in xs if not isinstance(x, float)]

        assert not_float(ga) == not_float(gc)


def test_enabling_one_model_does_not_change_other_streams() -> None:
    ideal = Simulator(default_config())
    noisy = Simulator(_noisy_cfg(), error_models=FACTORIES)
    ideal.reset(4)
    noisy.reset(4)
    for name in RNG_STREAMS:
        if name != "gyro":
            assert ideal._rngs[name].bit_generator.state == noisy._rngs[name].bit_generator.state


def test_missing_error_model_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="gyro"):
        Simulator(_noisy_cfg(), error_models={})


def test_robot_description_is_json_ready() -> None:
    sim = Simulator(default_config())
    d = json.loads(json.dumps(sim.robot_description()))
    assert d["wheel_base_m"] == pytest.approx(0.285)
    assert d["ticks_per_metre"] == pytest.approx(90284.0)
    assert len(d["sensors"]["ir"]["poses"]) == 16
    assert len(d["sensors"]["sonar"]["poses"]) == 9
    p = d["sensors"]["ir"]["poses"][0]
    assert set(p) == {"x", "y", "theta"} and p["theta"] == pytest.approx(math.radians(-5.7))


# ---------------------------------------------------------------------- config errors
@pytest.mark.parametrize(
    ("section", "bad", "suggest"),
    [
        (("sensors", "sonar"), "rate_hx", "rate_hz"),
        (("robot",), "wheel_bse_m", "wheel_base_m"),
        (("sim",), "dt", "dt_s"),
        (("sensors", "camera"), "fov", "fov_deg"),
    ],
)
def test_unknown_key_suggests_nearest(section: tuple[str, ...], bad: str, suggest: str) -> None:
    cfg = copy.deepcopy(default_config())
    t = cfg
    for s in section:
        t = t[s]
    t[bad] = 1
    with pytest.raises(ConfigError, match=f"did you mean '{suggest}'"):
        load_sim_config(cfg)


def test_rate_must_divide_the_step() -> None:
    cfg = copy.deepcopy(default_config())
    cfg["sensors"]["ir"]["rate_hz"] = 30            # 1 / (30 * 0.01) is not whole
    with pytest.raises(ConfigError, match=r"sensors\.ir"):
        load_sim_config(cfg)


def test_missing_key_and_bad_values() -> None:
    cfg = copy.deepcopy(default_config())
    del cfg["robot"]["wheel_base_m"]
    with pytest.raises(ConfigError, match="wheel_base_m"):
        load_sim_config(cfg)
    cfg = copy.deepcopy(default_config())
    cfg["sensors"]["ir"]["rays"] = 2
    with pytest.raises(ConfigError, match="odd"):
        load_sim_config(cfg)
    cfg = copy.deepcopy(default_config())
    cfg["sensors"]["ir"]["poses"] = [[0, 0]]
    with pytest.raises(ConfigError, match="poses"):
        load_sim_config(cfg)


def test_other_top_level_sections_are_ignored() -> None:
    cfg = copy.deepcopy(default_config())
    cfg["zenoh"] = {"anything": 1}
    assert load_sim_config(cfg).robot.name == "koala"
