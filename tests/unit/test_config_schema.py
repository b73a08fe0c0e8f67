"""The configuration schema's one policy (bridge/core/schema.py, config/README.md "Policy").

Every key comes from the file or from one documented default, which is the value
config/default.toml shows; unknown keys are errors with did-you-mean; types are strict; numbers
are finite and in range; errors are one line.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from conftest import commented_real_block
from koala_bridge.calibration.errors import ModelConfigError
from koala_bridge.calibration.model import declared_model
from koala_bridge.core.resources import default_config_path, default_dbc_path
from koala_bridge.core.schema import ConfigError, validate
from koala_bridge.runtime.buses import OpenBuses
from koala_bridge.runtime.endpoints import endpoints_of
from koala_bridge.runtime.localisation import (
    GridSettings,
    LocalisationSettings,
    OccupancySettings,
    PoseSettings,
    RobustSettings,
)
from koala_bridge.runtime.real_source import RealPorts
from koala_bridge.runtime.settings import (
    BridgeSettings,
    CanSettings,
    KteamSettings,
    LockstepSettings,
    MavlinkSettings,
    RangefindersSettings,
    RunSettings,
    ZenohSettings,
    apply_override,
    load_config,
    parse_override,
)
from koala_bridge.sim.battery import BatteryConfig
from koala_bridge.sim.config import StepConfig, load_sim_config
from koala_bridge.sim.noise import LookupTable
from koala_bridge.sim.robot import DriveConfig, RobotConfig
from koala_bridge.sim.sections import ERROR_PARAMS
from koala_bridge.sim.sensors.camera import CameraConfig
from koala_bridge.sim.sensors.compass import CompassConfig
from koala_bridge.sim.sensors.encoders import EncoderConfig
from koala_bridge.sim.sensors.gyro import GyroConfig
from koala_bridge.sim.sensors.ir import IrConfig
from koala_bridge.sim.sensors.sonar import SonarConfig
from koala_bridge.sim.world import EarthField

REPO = Path(__file__).resolve().parents[2]
DEFAULT = REPO / "config" / "default.toml"


def default() -> dict[str, Any]:
    return load_config(DEFAULT)


def table(doc: dict[str, Any], dotted: str) -> dict[str, Any]:
    node: Any = doc
    for part in dotted.split("."):
        node = node[part]
    return node


def _error_params(model: str) -> Any:
    import importlib

    module, name = ERROR_PARAMS[model]
    return getattr(importlib.import_module(module), name)


#: Every section class and the table of default.toml it types. Keys of a table that a class
#: does not own (its sub-tables, or the keys its error model owns) are checked by the others.
SECTIONS: list[tuple[Any, str]] = [
    (StepConfig, "sim"),
    (RobotConfig, "robot"),
    (DriveConfig, "robot.drive_error"),
    (_error_params("drive"), "robot.drive_error"),
    (IrConfig, "sensors.ir"),
    (_error_params("ir"), "sensors.ir"),
    (SonarConfig, "sensors.sonar"),
    (_error_params("sonar"), "sensors.sonar"),
    (EncoderConfig, "sensors.encoders"),
    (GyroConfig, "sensors.gyro"),
    (_error_params("gyro"), "sensors.gyro"),
    (CompassConfig, "sensors.compass"),
    (_error_params("compass"), "sensors.compass"),
    (CameraConfig, "sensors.camera"),
    (_error_params("camera"), "sensors.camera"),
    (BatteryConfig, "robot.battery"),
    (EarthField, "world.earth_field"),
    (RunSettings, "run"),
    (LockstepSettings, "lockstep"),
    (KteamSettings, "buses.kteam"),
    (RangefindersSettings, "buses.rangefinders"),
    (CanSettings, "buses.can"),
    (MavlinkSettings, "buses.mavlink"),
    (ZenohSettings, "zenoh"),
    (LocalisationSettings, "localisation"),
    (PoseSettings, "localisation.pose"),
    (GridSettings, "localisation.grid"),
    (OccupancySettings, "localisation.occupancy"),
    (RobustSettings, "localisation.robust"),
]

#: Fields that are built, not read from the file: the error model's params, and [robot]'s
#: [robot.drive_error] and [robot.battery] tables (read under their own names).
BUILT = {"errors", "drive", "battery"}


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, LookupTable) or isinstance(b, LookupTable):
        return a.rows() == b.rows()
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, float) and isinstance(b, float) and math.isinf(a):
        return a == b
    return bool(a == b)


@pytest.mark.parametrize(("cls", "where"), SECTIONS, ids=[f"{w}:{c.__name__}" for c, w in SECTIONS])
def test_every_field_is_in_default_toml_with_its_default(cls: Any, where: str) -> None:
    """The policy's one-default rule: every key is written in default.toml, and a field that has
    a default (may be left out of a file) has default.toml's value as that default."""
    doc = table(default(), where)
    for f in dataclasses.fields(cls):
        if f.name in BUILT:
            continue
        assert f.name in doc, f"[{where}] {f.name} is not documented in config/default.toml"
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            continue
        code_default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        # the section built from this key and the required ones, the others left to defaults
        required = {g.name: doc[g.name] for g in dataclasses.fields(cls) if g.name not in BUILT
                    and g.default is g.default_factory is dataclasses.MISSING}
        given = validate(cls, {**required, f.name: doc[f.name]}, where)
        assert _same(getattr(given, f.name), code_default), (
            f"[{where}] {f.name}: the code's default {code_default!r} differs from "
            f"config/default.toml's {doc[f.name]!r}"
        )


def test_default_toml_holds_no_key_the_schema_lacks() -> None:
    """Loading default.toml checks every key (unknown keys are errors); the sections above and
    [world] cover every table of the file."""
    config = default()
    load_sim_config(config)
    BridgeSettings.from_config(config)
    assert LocalisationSettings.from_config(config) is not None
    covered = {w for _, w in SECTIONS} | {"world", "world.start", "sensors", "buses"}
    tables = set()

    def walk(node: dict[str, Any], prefix: str) -> None:
        for k, v in node.items():
            if isinstance(v, dict):
                tables.add(f"{prefix}{k}")
                walk(v, f"{prefix}{k}.")

    walk(config, "")
    assert tables - covered == set()


def test_real_section_defaults_are_the_commented_block_of_default_toml() -> None:
    block = commented_real_block(DEFAULT)
    assert set(block) == {f.name for f in dataclasses.fields(RealPorts)}
    assert RealPorts.from_dict(block) == RealPorts()
    with pytest.raises(ConfigError, match=r"\[real\] section naming the robot's ports"):
        RealPorts.from_config({"real": block})    # every port "": none named


def test_loading_default_toml_gives_the_params_python_defaults() -> None:
    """A params object built in Python and the one read from the shipped file agree (the sonar
    late echo once defaulted to 0.0 in code and 0.3 in the file)."""
    s = load_sim_config(default()).sensors
    assert s.sonar.errors.late_echo_probability == 0.3
    for model, errors in (("ir", s.ir.errors), ("sonar", s.sonar.errors),
                          ("gyro", s.gyro.errors), ("compass", s.compass.errors),
                          ("camera", s.camera.errors)):
        cls = _error_params(model)
        python = cls()
        for f in dataclasses.fields(cls):
            assert _same(getattr(errors, f.name), getattr(python, f.name)), (model, f.name)


# ------------------------------------------------------------------------------ unknown keys


@pytest.mark.parametrize(("override", "message"), [
    ("sensors.sonar.late_echo_probabilty=0.1",
     r"\[sensors.sonar\] unknown key 'late_echo_probabilty'; did you mean "
     r"'late_echo_probability' \(sensors.sonar.late_echo_probability\)\?"),
    ("robot.drive_error.wall_tracton_min=0.1",
     r"did you mean 'wall_traction_min' \(robot.drive_error.wall_traction_min\)"),
    ("localisation.pose.gate_probabilty=0.9",
     r"\[localisation.pose\] unknown key 'gate_probabilty'; did you mean 'gate_probability' "
     r"\(localisation.pose.gate_probability\)"),
    ("buses.can.dcb=\"x.dbc\"", r"did you mean 'dbc' \(buses.can.dbc\)"),
    ("world.earth_field.north=0", r"did you mean 'north_deg' \(world.earth_field.north_deg\)"),
])
def test_unknown_nested_key_names_the_full_dotted_key(override: str, message: str) -> None:
    cfg = apply_override(default(), *parse_override(override))
    with pytest.raises(ConfigError, match=message):
        load_sim_config(cfg)
        BridgeSettings.from_config(cfg)
        LocalisationSettings.from_config(cfg)


# ------------------------------------------------------------------------------ types


@pytest.mark.parametrize(("override", "message"), [
    ('robot.wheel_base_m="0.285"', r"\[robot\] 'wheel_base_m' must be a number, got '0.285'"),
    ("robot.wheel_base_m=true", r"\[robot\] 'wheel_base_m' must be a number, got True"),
    ("sensors.gyro.bias_rad_s=false", r"'bias_rad_s' must be a number, got False"),
    ("sensors.ir.rays=3.0", r"'rays' must be an integer, got 3.0"),
    ("sensors.gyro.ideal=1", r"'ideal' must be bool"),
    ('sensors.sonar.poses=[[0, 0, "90"]]', r"'poses' must be a non-empty list"),
    ('sensors.compass.hard_iron_uT=[1, 2, "3"]', r"'hard_iron_uT'\[2\] must be a number"),
    ("sensors.ir.distance_error=[[0, 0], [1, true]]", r"'distance_error' must be rows of numbers"),
    ('buses.mavlink.port="14550"', r"\[buses.mavlink\] 'port' must be"),
    ('localisation.grid.p_hit="0.9"', r"'p_hit' must be a number"),
    ('world.earth_field.vertical_uT="-43"', r"'vertical_uT' must be a number"),
])
def test_types_are_strict(override: str, message: str) -> None:
    cfg = apply_override(default(), *parse_override(override))
    with pytest.raises(ConfigError, match=message):
        load_sim_config(cfg)
        BridgeSettings.from_config(cfg)
        LocalisationSettings.from_config(cfg)


def test_an_int_is_a_float_and_a_bare_word_is_a_string() -> None:
    cfg = default()
    for override in ("robot.wheel_base_m=1", "robot.name=k2", "sensors.gyro.bias_rad_s=0"):
        cfg = apply_override(cfg, *parse_override(override))
    sim = load_sim_config(cfg)
    assert sim.robot.wheel_base_m == 1.0 and isinstance(sim.robot.wheel_base_m, float)
    assert BridgeSettings.from_config(cfg).zenoh.prefix == "koala/k2"


# ------------------------------------------------------------------------------ ranges


@pytest.mark.parametrize(("override", "message"), [
    ("sim.dt_s=1e-9", r"\[sim\] 'dt_s' must be >= 0.0001"),
    ("sim.dt_s=0", r"'dt_s' must be >= 0.0001"),
    ("sim.dt_s=nan", r"'dt_s' must be a finite number"),
    ("world.earth_field.horizontal_uT=nan", r"\[world.earth_field\] 'horizontal_uT' must be a "
                                            r"finite number"),
    ("world.earth_field.horizontal_uT=inf", r"'horizontal_uT' must be a finite number"),
    ("robot.wheel_base_m=0", r"\[robot\] 'wheel_base_m' must be > 0"),
    ("robot.wheel_base_m=-0.285", r"'wheel_base_m' must be > 0"),
    ("robot.wheel_base_m=inf", r"'wheel_base_m' must be a finite number"),
    ("robot.ticks_per_metre=1e300", r"'ticks_per_metre' must be a plausible number"),
    ("sensors.gyro.bias_correlation_time_s=nan", r"'bias_correlation_time_s' must be a number"),
    ("sensors.gyro.bias_correlation_time_s=0", r"'bias_correlation_time_s' must be > 0"),
    ("sensors.gyro.gyroscope_noise_density=-1e-4", r"'gyroscope_noise_density' must be >= 0"),
    ("sensors.sonar.late_echo_probability=1.5", r"'late_echo_probability' must be <= 1"),
    ("sensors.compass.rate_hz=-50", r"\[sensors.compass\] 'rate_hz' must be > 0"),
    ("sensors.camera.fov_deg=400", r"'fov_deg' must be <= 360"),
    ("world.landmarks=[{id = 1, x = nan, y = 0}]", r"\[world.landmarks\[0\]\] 'x' must be a "
                                                    r"finite number"),
    ("zenoh.pose_rate_hz=inf", r"\[zenoh\] 'pose_rate_hz' must be a finite number"),
    ("buses.motor_watchdog_s=-1", r"\[buses\] 'motor_watchdog_s' must be >= 0"),
    ("buses.mavlink.heartbeat_hz=0", r"'heartbeat_hz' must be > 0"),
    ("localisation.occupancy.resolution_m=0", r"'resolution_m' must be > 0"),
    ("localisation.pose.gate_probability=1", r"'gate_probability' must be < 1"),
    ("localisation.robust.ir_usable_counts=[900, 100]", r"ir_usable_counts.*low < high"),
    ("localisation.robust.lost_reject_ratio=1.5", r"lost_reject_ratio"),
])
def test_numbers_are_finite_and_in_range(override: str, message: str) -> None:
    cfg = apply_override(default(), *parse_override(override))
    with pytest.raises(ConfigError, match=message) as e:
        load_sim_config(cfg)
        BridgeSettings.from_config(cfg)
        LocalisationSettings.from_config(cfg)
    assert "\n" not in str(e.value)


def test_inf_where_it_has_a_meaning() -> None:
    """[sensors.gyro] bias_correlation_time_s = inf is the pure random walk (Kalibr)."""
    cfg = apply_override(default(), *parse_override("sensors.gyro.bias_correlation_time_s=inf"))
    assert load_sim_config(cfg).sensors.gyro.errors.bias_correlation_time_s == math.inf


def test_params_built_in_python_are_checked_too() -> None:
    sonar = _error_params("sonar")
    with pytest.raises(ValueError, match="late_echo_probability"):
        sonar(late_echo_probability=2.0)
    with pytest.raises(ConfigError, match=r"\[sensors.sonar\] 'late_echo_probability'"):
        sonar.from_dict({"late_echo_probability": math.nan})


# ------------------------------------------------------------------------------ --set


@pytest.mark.parametrize("text", [
    'zenoh.listen=["tcp/127.0.0.1:7447"',
    "buses.can.dbc=\"koala.dbc",
    "sensors.compass.hard_iron_uT=[1, 2,, 3]",
    "real.can_options={host = }",
])
def test_a_set_value_that_is_not_toml_is_one_clear_line(text: str) -> None:
    with pytest.raises(ConfigError, match=r"^override [a-zA-Z_.]+: .* is not a TOML value") as e:
        parse_override(text)
    assert "\n" not in str(e.value)


def test_a_set_value_is_one_toml_value() -> None:
    with pytest.raises(ConfigError, match="more than one TOML value"):
        parse_override("run.clock=\"fast\"\nzenoh.mode = \"client\"")
    assert parse_override("robot.name=k2") == (["robot", "name"], "k2")
    assert parse_override("real.kteam=/dev/ttyUSB0") == (["real", "kteam"], "/dev/ttyUSB0")


def test_a_bare_word_for_a_number_is_refused_by_the_schema() -> None:
    cfg = apply_override(default(), *parse_override("robot.wheel_base_m=0.28.5"))
    with pytest.raises(ConfigError, match=r"'wheel_base_m' must be a number, got '0.28.5'"):
        load_sim_config(cfg)


# ------------------------------------------------------------------------------ the DBC key


def test_dbc_key_defaults_to_the_shipped_database(tmp_path: Path) -> None:
    can = BridgeSettings.from_config(default()).buses.can
    assert can.dbc == "" and can.dbc_path == default_dbc_path() and can.dbc_path.is_file()
    copy_ = tmp_path / "mine.dbc"
    copy_.write_bytes(default_dbc_path().read_bytes())
    cfg = apply_override(default(), *parse_override(f'buses.can.dbc="{copy_}"'))
    can = BridgeSettings.from_config(cfg).buses.can
    assert can.dbc_path == copy_
    assert can.codec().frame_ids["WheelOdometry"] > 0


def test_a_config_from_before_the_dbc_key_loads() -> None:
    cfg = default()
    del cfg["buses"]["can"]["dbc"]
    assert BridgeSettings.from_config(cfg).buses.can.dbc_path == default_dbc_path()


def test_a_missing_dbc_matters_only_when_a_can_bus_is_on(tmp_path: Path) -> None:
    missing = tmp_path / "nope.dbc"
    cfg = apply_override(default(), *parse_override(f'buses.can.dbc="{missing}"'))
    with pytest.raises(ConfigError, match=r"\[buses.can\] 'dbc': cannot load the CAN database"):
        BridgeSettings.from_config(cfg).buses.can.codec()
    for bus in ("socketcand", "slcan", "virtual", "socketcan"):
        cfg = apply_override(cfg, ["buses", "can", bus], False)
    can = BridgeSettings.from_config(cfg).buses.can
    assert not can.enabled
    assert can.codec().frame_ids == BridgeSettings.from_config(default()).buses.can.codec(
    ).frame_ids


def test_endpoints_name_the_configured_dbc_and_none_without_can(tmp_path: Path) -> None:
    mine = tmp_path / "mine.dbc"
    mine.write_bytes(default_dbc_path().read_bytes())
    settings = BridgeSettings.from_config(
        apply_override(default(), *parse_override(f'buses.can.dbc="{mine}"')))
    buses = OpenBuses()
    assert endpoints_of(buses, settings).dbc is None
    buses.can["can.virtual"] = SimpleNamespace(  # type: ignore[assignment]
        endpoint=SimpleNamespace(channel="koala"))
    assert endpoints_of(buses, settings).dbc == str(mine.resolve())


# ------------------------------------------------------------------------------ calibration


def test_calibration_reads_the_typed_sim_config() -> None:
    """calibration/model.py takes values from load_sim_config (no defaults of its own): a key it
    does not name comes from default.toml (max_counts), a wrong type is refused."""
    model = declared_model(
        {"sensors": {"ir": {"ambient_saturation": 0.1, "ambient_counts": 500},
                     "gyro": {"rate_hz": 50, "bias_rad_s": 0.01}}}, {})
    full = load_sim_config(default()).sensors.ir.max_counts
    assert model.ir_gain == pytest.approx(1.0 - 0.1 * 500 / full)
    assert model.gyro_bias_rad_s == 0.01 and model.gyro_sample_interval_s == pytest.approx(0.02)
    with pytest.raises(ModelConfigError, match=r"'bias_rad_s' must be a number"):
        declared_model({"sensors": {"gyro": {"bias_rad_s": "0.01"}}}, {})
    # nothing named, nothing declared
    empty = declared_model({}, {})
    assert (empty.ir_gain, empty.gyro_bias_rad_s, empty.ir_curve) == (1.0, 0.0, None)


def test_shipped_configs_load(tmp_path: Path) -> None:
    for path in (default_config_path(), REPO / "config" / "ideal.toml"):
        config = load_config(path)
        load_sim_config(config)
        BridgeSettings.from_config(config)
    # the deep copy a test or a user edits is independent of the file's
    cfg = copy.deepcopy(default())
    cfg["sim"]["dt_s"] = 0.005
    assert load_sim_config(cfg).sim.dt_s == 0.005


def test_each_sensor_section_lives_in_its_sensor_module() -> None:
    """sim/sensors/<name>.py (parameters + truth) and sim/models/<name>.py (error model) are the
    whole sensor: the section SensorsConfig composes for <name> is defined in its truth module."""
    import dataclasses
    import importlib


    sensors = load_sim_config(default()).sensors
    for f in dataclasses.fields(sensors):
        cls = type(getattr(sensors, f.name))
        assert cls.__module__ == f"koala_bridge.sim.sensors.{f.name}", (f.name, cls.__module__)
        assert getattr(importlib.import_module(cls.__module__), cls.__name__) is cls
    assert RobotConfig.__module__ == DriveConfig.__module__ == "koala_bridge.sim.robot"
