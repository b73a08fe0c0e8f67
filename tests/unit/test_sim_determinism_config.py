"""Determinism, RNG streams, the error-model seam and typed config errors."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import tomllib
from typing import Any

import numpy as np
import pytest
from _sim_support import DEFAULT, IDEAL, default_config, ideal_config
from koala_bridge.core.schema import ConfigError
from koala_bridge.sim.config import load_sim_config
from koala_bridge.sim.noise import BlockStream
from koala_bridge.sim.simulator import RNG_STREAMS, Simulator
from koala_bridge.sim.types import GyroReading, Readings, WheelCommand
from koala_bridge.sim.world import World


def _flatten(r: Readings) -> list[Any]:
    out: list[Any] = [r.t, r.pose, r.wheel_speeds, r.collided]
    for name in ("ir", "sonar", "odometry", "gyro", "compass", "camera"):
        v = getattr(r, name)
        if v is None:
            out.append(None)
            continue
        for f in dataclasses.fields(v):
            x = getattr(v, f.name)
            out.append(x.tobytes() if isinstance(x, np.ndarray) else x)
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
    cfg = ideal_config()
    assert _run(cfg, 1, 200) == _run(cfg, 2, 200)


class _NoisyGyro:
    """A stand-in error model: adds N(0, sigma) from the gyro's own stream."""

    def __init__(self, sigma: float, rng: np.random.Generator) -> None:
        self.sigma = sigma
        self.bias = float(rng.normal())            # turn-on state drawn at reset

    def measure(self, truth: Any, variates: BlockStream) -> GyroReading:
        noise = self.sigma * float(variates.standard_normal())
        return GyroReading(truth.yaw_rate + self.bias + noise, truth.yaw_rate)


def _noisy_cfg() -> dict:
    cfg = copy.deepcopy(ideal_config())
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
    ideal = Simulator(ideal_config())
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
    assert d["ticks_per_metre"] == pytest.approx(1 / 0.045e-3)       # classic Koala, koala.c
    # D,127,127 (pulses per 10 ms) is the full wheel speed: 127 x 4.5 mm/s
    assert 127 / d["ticks_per_metre"] / d["speed_unit_s"] == pytest.approx(
        d["max_wheel_speed_mps"], rel=1e-6)
    assert len(d["sensors"]["ir"]["poses"]) == 16
    assert len(d["sensors"]["sonar"]["poses"]) == 9
    p = d["sensors"]["ir"]["poses"][0]
    assert set(p) == {"x", "y", "theta"} and p["theta"] == pytest.approx(math.radians(-5.7))
    # The magnetic sources' 1/d^2 law is clamped at this distance (docs/protocols.md, "world").
    assert d["sensors"]["compass"]["min_source_distance_m"] == pytest.approx(0.05)


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


@pytest.mark.parametrize("top, middle, where", [
    ("+---+---+---+", "|   #       |",
     r"line 2, column 5: '#' in the wall slot west of cell \(1, 0\)"),
    ("+---+---+---+", "| - |       |", r"line 2, column 3: '-' in cell \(0, 0\)"),
    ("+---+---+---+", "|   |  x    |", r"line 2, column 8: 'x' in cell \(1, 0\)"),
    ("+---+---+---+", "|           | ;", r"line 2, column 15: ';' in the map's right margin"),
    ("+---+-*-+---+", "|   |    #  |",
     r"line 1, column 7: '\*' in the wall slot north of cell \(1, 0\)"),
])
def test_a_stray_map_character_is_an_error_naming_where(top: str, middle: str, where: str) -> None:
    # A typo must not silently change the world (a '#' one column off used to vanish).
    cfg = copy.deepcopy(default_config())
    cfg["world"]["map"] = "\n".join([top, middle, "+---+---+---+"])
    cfg["world"].pop("start", None)
    with pytest.raises(ConfigError, match=where):
        load_sim_config(cfg)


def test_every_shipped_world_loads() -> None:
    for path in sorted({DEFAULT, IDEAL, *(DEFAULT.parent / "worlds").glob("*.toml")}):
        with path.open("rb") as f:
            world = World.from_dict(tomllib.load(f)["world"])
        assert world.cols > 0 and world.rows > 0, path


def test_other_top_level_sections_are_ignored() -> None:
    cfg = copy.deepcopy(default_config())
    cfg["zenoh"] = {"anything": 1}
    assert load_sim_config(cfg).robot.name == "koala"


def test_default_runs_every_model_and_ideal_toml_differs_only_in_the_switches() -> None:
    with DEFAULT.open("rb") as f:
        default = tomllib.load(f)
    with IDEAL.open("rb") as f:
        ideal = tomllib.load(f)
    tables = [("robot", "drive_error")] + [("sensors", n) for n in default["sensors"]]
    for path in tables:
        d, i = default[path[0]][path[1]], ideal[path[0]][path[1]]
        assert i["ideal"] is True, path
        assert d["ideal"] is (path == ("sensors", "encoders")), path   # encoders: no model
        d["ideal"] = i["ideal"] = None
    assert default == ideal


#: The keys in which koala25.toml (the Koala 2.5) differs from default.toml.
KOALA25_KEYS = {
    ("robot", "name"), ("robot", "ticks_per_metre"), ("robot", "wheel_diameter_m"),
    ("robot", "wheel_base_m"), ("robot", "max_wheel_speed_mps"),
    ("robot", "battery", "chemistry"), ("robot", "battery", "voltage_full_V"),
    ("robot", "battery", "voltage_empty_V"), ("buses", "kteam", "dialect"),
}


def test_koala25_toml_is_default_toml_with_the_koala25_keys() -> None:
    with DEFAULT.open("rb") as f:
        default = tomllib.load(f)
    with (DEFAULT.parent / "koala25.toml").open("rb") as f:
        k25 = tomllib.load(f)
    for path in KOALA25_KEYS:
        d, k = default, k25
        for key in path[:-1]:
            d, k = d[key], k[key]
        assert d[path[-1]] != k[path[-1]], path
        d[path[-1]] = k[path[-1]] = None
    assert default == k25
    with (DEFAULT.parent / "koala25.toml").open("rb") as f:
        assert load_sim_config(tomllib.load(f)).robot.ticks_per_metre == 90284.0


def test_encoders_have_no_error_model() -> None:
    cfg = copy.deepcopy(default_config())
    cfg["sensors"]["encoders"]["ideal"] = False
    with pytest.raises(ConfigError, match=r"sensors\.encoders.*drive_error"):
        load_sim_config(cfg)


def test_shared_keys_have_one_owner() -> None:
    cfg = load_sim_config(default_config())
    s = cfg.sensors
    # the sensor's validated values reach its model's params
    assert s.sonar.errors.min_range_m == s.sonar.min_range_m
    assert (s.camera.errors.min_range_m, s.camera.errors.max_range_m) == (
        s.camera.min_range_m, s.camera.max_range_m)
    assert (s.ir.errors.ambient_counts, s.ir.errors.max_counts) == (
        s.ir.ambient_counts, s.ir.max_counts)
    for sensor in (s.ir, s.sonar, s.gyro, s.compass, s.camera):
        assert sensor.errors.ideal is sensor.ideal is False
    # a model key is validated by the model, with a suggestion when misspelt
    bad = copy.deepcopy(default_config())
    bad["sensors"]["sonar"]["glitch_probabilty"] = 0.1
    with pytest.raises(ConfigError, match="did you mean 'glitch_probability'"):
        load_sim_config(bad)
    bad = copy.deepcopy(default_config())
    bad["sensors"]["ir"]["ambient_counts"] = 2000
    with pytest.raises(ConfigError, match="max_counts"):
        load_sim_config(bad)
