"""The declared sensor model: what MODEL.toml (the bridge's config) and ``meta.json`` state.

The simulator owns the config schema (``sim/config.py``, ``config/default.toml``); this module
reads, under the simulator's own names, the keys calibration needs, tolerantly (a missing key
means ideal/nominal, so a partial MODEL.toml or none at all is fine), and applies the precedence
of the bundle format: for data from another robot, ``meta.json`` ``robot``/``sensor`` values
override the config file.

Keys read (units in the key name where not SI)::

    [robot]            ticks_per_metre, wheel_base_m, wheel_diameter_ratio
    [sensors.gyro]     ideal, rate_hz, bias_rad_s, scale_factor_error, turn_on_bias_sigma
    [sensors.compass]  ideal, hard_iron_uT = [x, y, z], soft_iron = [[3x3]]
    [sensors.ir]       ideal, response_range_m, response_counts, reflectivity,
                       ambient_saturation, ambient_counts, max_counts, per_sensor_offset_counts
    [sensors.sonar]    ideal, critical_angle_deg, min_range_m, max_range_m, distance_error
    [sensors.compass]  motor_uT_per_A, motor_current_A_per_mps, min_source_distance_m
    [sensors.camera]   ideal, p_recog, dist, d_mid_m, far_doubling_m, bearing_sigma_deg
    [world]            earth_field, magnetic_sources (a heading reference with position)

``meta.json`` ``robot``: the ``[robot]`` keys and ``start_pose``; ``sensor.gyro``:
``bias_rad_s``, ``scale_factor_error``.
"""

from __future__ import annotations

import logging
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from koala_bridge.calibration.errors import ModelConfigError

log = logging.getLogger(__name__)


#: Earth field (x, y, z) uT world frame, local sources ((x, y, strength_uT), ...), clamp distance
WorldField = tuple[tuple[float, float, float], tuple[tuple[float, float, float], ...], float]


@dataclass(frozen=True)
class StartPose:
    x: float
    y: float
    theta: float


@dataclass(frozen=True)
class DeclaredModel:
    """Declared values after precedence (meta.json > MODEL.toml > ideal).

    ``config`` is the TOML document as read (written back, with found effects, by
    ``--write-config``); ``sources`` says where each declared value came from.
    """

    config: Mapping[str, Any]
    ticks_per_metre: float | None = None
    wheel_base_m: float | None = None
    wheel_diameter_ratio: float = 1.0
    start_pose: StartPose | None = None
    gyro_bias_rad_s: float = 0.0
    gyro_scale_error: float = 0.0
    #: sigma of the declared turn-on bias (drawn per run around gyro_bias_rad_s): a nuisance
    gyro_turn_on_bias_sigma: float = 0.0
    #: the declared sample is the mean rate over the interval before its stamp (the simulator's
    #: rate-integrating gyro at [sensors.gyro] rate_hz); None: the instantaneous rate
    gyro_sample_interval_s: float | None = None
    compass_hard_iron: tuple[float, float, float] = (0.0, 0.0, 0.0)
    compass_soft_iron: tuple[tuple[float, ...], ...] = (
        (1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, 0.0, 1.0),
    )
    #: motor-current disturbance M k (v_left, v_right) (sim/models/compass.py): (3, 2) uT per m/s
    compass_motor_uT_per_mps: tuple[tuple[float, ...], ...] | None = None
    #: the world's magnetic field, for a heading reference with position: Earth (3,) uT world
    #: frame, local sources ((x, y, strength_uT), ...), clamp distance (sim/sensors/compass.py)
    compass_world: WorldField | None = None
    ir_curve: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    #: counts = ir_gain * curve(range) + offset: reflectivity and the ambient-light loss
    ir_gain: float = 1.0
    ir_per_sensor_offset: tuple[float, ...] = ()
    #: number of IR sensors the config declares ([sensors.ir] poses), for per-sensor keys
    ir_sensor_count: int | None = None
    #: camera (sim/models/camera.py): wrong ids declared (observations are re-associated to
    #: the nearest predicted landmark), and the distance model's mean error
    #: eps_far sqrt(2/pi), eps_far = dist d_mid 2^((d - d_mid) / far_doubling)
    camera_wrong_ids: bool = False
    camera_far: tuple[float, float, float] | None = None  # dist, d_mid_m, far_doubling_m
    camera_bearing_sigma_rad: float = 0.0
    #: the sonar's echo rule: beyond this incidence the declared model predicts no direct echo
    sonar_critical_angle_rad: float | None = None
    #: the sonar's reporting range (min_range_m, max_range_m) and its distance-error table
    #: ([range_m, sigma_m] rows): readings that could be censored there are not residuals
    sonar_range_m: tuple[float, float] | None = None
    sonar_distance_error: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    sources: Mapping[str, str] = field(default_factory=dict)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelConfigError(f"{where} must be a number, got {value!r}")
    return float(value)


def _section(doc: Mapping[str, Any], *path: str) -> Mapping[str, Any]:
    node: Any = doc
    for key in path:
        node = node.get(key, {}) if isinstance(node, Mapping) else {}
    return node if isinstance(node, Mapping) else {}


def read_config(path: Path | None) -> dict[str, Any]:
    """Parse MODEL.toml; ``None`` gives an empty (all-ideal) model."""
    if path is None:
        return {}
    try:
        with Path(path).open("rb") as fh:
            config = tomllib.load(fh)
    except OSError as e:
        raise ModelConfigError(f"cannot read model config {path}: {e}") from e
    except tomllib.TOMLDecodeError as e:
        raise ModelConfigError(f"{path} is not valid TOML: {e}") from e
    check_config(config, str(path))
    return config


def _laid_over(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        old = out.get(key)
        both = isinstance(old, Mapping) and isinstance(value, Mapping)
        out[key] = _laid_over(old, value) if both else value  # type: ignore[arg-type]
    return out


def check_config(config: Mapping[str, Any], where: str) -> None:
    """The same checks as ``koala-bridge run``: an unknown section or key, or a value of the
    wrong kind, is an error naming it (and the nearest valid name), not a key silently
    ignored. MODEL.toml may be partial: it is laid over the shipped ``config/default.toml``
    first, and the bridge's and the simulator's own loaders check the result."""
    from koala_bridge.core.resources import default_config_path
    from koala_bridge.core.schema import ConfigError
    from koala_bridge.runtime.localisation import LocalisationSettings
    from koala_bridge.runtime.settings import BridgeSettings, load_config, reject_unknown_sections
    from koala_bridge.sim.config import load_sim_config

    if not config:
        return
    merged = _laid_over(load_config(default_config_path()), config)
    try:
        reject_unknown_sections(merged)
        BridgeSettings.from_config(merged)
        load_sim_config(merged)
        LocalisationSettings.from_config(merged)
    except ConfigError as e:
        raise ModelConfigError(f"{where}: {e}") from e


def declared_model(config: Mapping[str, Any], meta: Mapping[str, Any]) -> DeclaredModel:
    """Combine the config with a bundle's ``meta.json`` (meta wins) into a DeclaredModel."""
    sources: dict[str, str] = {}
    robot = _section(config, "robot")
    meta_robot = meta.get("robot", {}) if isinstance(meta.get("robot"), Mapping) else {}

    def pick(key: str) -> float | None:
        if isinstance(meta_robot.get(key), int | float):
            sources[key] = "meta.json robot"
            return float(meta_robot[key])
        if key in robot:
            sources[key] = "config [robot]"
            return _number(robot[key], f"[robot] {key}")
        return None

    tpm = pick("ticks_per_metre")
    base = pick("wheel_base_m")
    ratio = pick("wheel_diameter_ratio")
    start = None
    sp = meta_robot.get("start_pose")
    if isinstance(sp, Mapping) and all(isinstance(sp.get(k), int | float) for k in ("x", "y")):
        theta = sp.get("theta")
        if not isinstance(theta, int | float) and isinstance(sp.get("theta_deg"), int | float):
            theta = np.deg2rad(sp["theta_deg"])
        start = StartPose(float(sp["x"]), float(sp["y"]), float(theta or 0.0))
        sources["start_pose"] = "meta.json robot"

    gyro = _section(config, "sensors", "gyro")
    meta_sensor = meta.get("sensor", {}) if isinstance(meta.get("sensor"), Mapping) else {}
    meta_gyro = meta_sensor.get("gyro") if isinstance(meta_sensor.get("gyro"), Mapping) else {}
    ideal_gyro = bool(gyro.get("ideal", False))

    def gyro_value(key: str) -> float:
        if ideal_gyro:
            return 0.0
        return _number(gyro.get(key, 0.0), f"[sensors.gyro] {key}")

    bias = gyro_value("bias_rad_s")
    scale = gyro_value("scale_factor_error")
    turn_on = gyro_value("turn_on_bias_sigma")
    if isinstance(meta_gyro, Mapping):
        if isinstance(meta_gyro.get("bias_rad_s"), int | float):
            bias, turn_on = float(meta_gyro["bias_rad_s"]), 0.0
        if isinstance(meta_gyro.get("scale_factor_error"), int | float):
            scale = float(meta_gyro["scale_factor_error"])
    interval = None
    if "rate_hz" in gyro:
        interval = 1.0 / _number(gyro["rate_hz"], "[sensors.gyro] rate_hz")

    compass = _section(config, "sensors", "compass")
    hard = (0.0, 0.0, 0.0)
    soft: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    if not compass.get("ideal", False):
        if "hard_iron_uT" in compass:
            h = [_number(v, "[sensors.compass] hard_iron_uT") for v in compass["hard_iron_uT"]]
            hard = (h + [0.0, 0.0, 0.0])[:3]  # type: ignore[assignment]
        if "soft_iron" in compass:
            s = np.asarray(compass["soft_iron"], dtype=float)
            if s.shape != (3, 3):
                raise ModelConfigError("[sensors.compass] soft_iron must be a 3x3 array")
            soft = tuple(tuple(float(v) for v in row) for row in s)

    motor = None
    if not compass.get("ideal", False) and "motor_uT_per_A" in compass:
        m = np.asarray(compass["motor_uT_per_A"], dtype=float)
        if m.shape != (3, 2):
            raise ModelConfigError("[sensors.compass] motor_uT_per_A must be 3 rows of 2")
        k = _number(
            compass.get("motor_current_A_per_mps", 0.0), "[sensors.compass] motor_current_A_per_mps"
        )
        if np.any(m * k != 0):
            motor = tuple(tuple(float(v) for v in row) for row in m * k)
    world = _world_field(config, compass)

    ir = _section(config, "sensors", "ir")
    curve = None
    gain = 1.0
    offsets: tuple[float, ...] = ()
    if not ir.get("ideal", False):
        if "response_range_m" in ir or "response_counts" in ir:
            r = tuple(
                _number(v, "[sensors.ir] response_range_m") for v in ir.get("response_range_m", [])
            )
            c = tuple(
                _number(v, "[sensors.ir] response_counts") for v in ir.get("response_counts", [])
            )
            if len(r) != len(c) or len(r) < 2:
                raise ModelConfigError(
                    "[sensors.ir] response_range_m and response_counts need equal lengths >= 2"
                )
            curve = (r, c)
        # sim/models/ir.py: c = rho R(d) (1 - ambient_saturation A / max_counts) + o_s + noise
        refl = _number(ir.get("reflectivity", 1.0), "[sensors.ir] reflectivity")
        sat = _number(ir.get("ambient_saturation", 0.0), "[sensors.ir] ambient_saturation")
        full = _number(ir.get("max_counts", 1023), "[sensors.ir] max_counts")
        amb = min(_number(ir.get("ambient_counts", 0.0), "[sensors.ir] ambient_counts"), full)
        gain = refl * (1.0 - sat * amb / full)
        offsets = tuple(
            _number(v, "[sensors.ir] per_sensor_offset_counts")
            for v in ir.get("per_sensor_offset_counts", [])
        )
    sonar = _section(config, "sensors", "sonar")
    critical = None
    if not sonar.get("ideal", False) and "critical_angle_deg" in sonar:
        critical = float(
            np.deg2rad(_number(sonar["critical_angle_deg"], "[sensors.sonar] critical_angle_deg"))
        )
    camera = _section(config, "sensors", "camera")
    wrong_ids, far, bearing_sigma = False, None, 0.0
    if not camera.get("ideal", True if not camera else False):
        wrong_ids = _number(camera.get("p_recog", 0.0), "[sensors.camera] p_recog") > 0
        if all(k in camera for k in ("dist", "d_mid_m", "far_doubling_m")):
            far = tuple(
                _number(camera[k], f"[sensors.camera] {k}")
                for k in ("dist", "d_mid_m", "far_doubling_m")
            )
        bearing_sigma = float(
            np.deg2rad(
                _number(camera.get("bearing_sigma_deg", 0.0), "[sensors.camera] bearing_sigma_deg")
            )
        )
    sonar_range = None
    sonar_table = None
    if not sonar.get("ideal", False) and {"min_range_m", "max_range_m"} <= set(sonar):
        sonar_range = (
            _number(sonar["min_range_m"], "[sensors.sonar] min_range_m"),
            _number(sonar["max_range_m"], "[sensors.sonar] max_range_m"),
        )
        rows = np.asarray(sonar.get("distance_error", []), dtype=float)
        if rows.ndim == 2 and rows.shape[0] >= 1 and rows.shape[1] >= 2:
            sonar_table = (tuple(rows[:, 0]), tuple(rows[:, 1]))
    return DeclaredModel(
        config=config,
        ticks_per_metre=tpm,
        wheel_base_m=base,
        wheel_diameter_ratio=1.0 if ratio is None else ratio,
        start_pose=start,
        gyro_bias_rad_s=bias,
        gyro_scale_error=scale,
        gyro_turn_on_bias_sigma=turn_on,
        gyro_sample_interval_s=interval,
        compass_hard_iron=hard,
        compass_soft_iron=soft,
        compass_motor_uT_per_mps=motor,
        compass_world=world,
        ir_curve=curve,
        ir_gain=gain,
        ir_per_sensor_offset=offsets,
        ir_sensor_count=len(ir["poses"]) if isinstance(ir.get("poses"), list) else None,
        sonar_critical_angle_rad=critical,
        sonar_range_m=sonar_range,
        sonar_distance_error=sonar_table,
        camera_wrong_ids=wrong_ids,
        camera_far=far,  # type: ignore[arg-type]
        camera_bearing_sigma_rad=bearing_sigma,
        sources=sources,
    )


def _world_field(config: Mapping[str, Any], compass: Mapping[str, Any]) -> WorldField | None:
    """The declared world's magnetic field (``[world.earth_field]``, ``[[world.magnetic_sources]]``)
    when it has local sources; None otherwise (a uniform field: north is a nuisance anyway)."""
    world = _section(config, "world")
    sources = world.get("magnetic_sources") or []
    earth = _section(world, "earth_field")
    if not sources or not earth:
        return None
    try:
        h = _number(earth["horizontal_uT"], "[world.earth_field] horizontal_uT")
        v = _number(earth["vertical_uT"], "[world.earth_field] vertical_uT")
        north = np.deg2rad(_number(earth["north_deg"], "[world.earth_field] north_deg"))
        src = tuple(
            (
                _number(m["x"], "[[world.magnetic_sources]] x"),
                _number(m["y"], "[[world.magnetic_sources]] y"),
                _number(m["strength_uT"], "[[world.magnetic_sources]] strength_uT"),
            )
            for m in sources
        )
    except (KeyError, TypeError) as e:
        raise ModelConfigError(f"[world] magnetic field incomplete: {e}") from e
    dmin = _number(compass.get("min_source_distance_m", 0.05), "min_source_distance_m")
    return (float(h * np.cos(north)), float(h * np.sin(north)), v), src, dmin
