"""The declared sensor model: what MODEL.toml (the bridge's config) and ``meta.json`` state.

The simulator owns the config schema (``sim/config.py``, ``config/default.toml``); this module
takes the values calibration needs from the simulator's typed config of MODEL.toml (laid over
``config/default.toml``, checked as ``koala-bridge run`` checks it), and declares an effect only
where MODEL.toml names its key (a key it leaves out is an absent effect, so a partial MODEL.toml
or none at all is fine). It applies the precedence of the bundle format: for data from another
robot, ``meta.json`` ``robot``/``sensor`` values override the config file.

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

``meta.json`` ``robot``: the ``[robot]`` keys (``tick_size_m``, metres per tick, for
``ticks_per_metre``) and ``start_pose``; ``sensor.gyro``:
``bias_rad_s``, ``scale_factor_error``.
"""

from __future__ import annotations

import copy
import logging
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from koala_bridge.calibration.errors import ModelConfigError

if TYPE_CHECKING:
    from koala_bridge.sim.config import SimConfig

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
    #: share of sonar readings the declared model makes spurious (glitch_probability: U(min, max))
    sonar_glitch_probability: float = 0.0
    sources: Mapping[str, str] = field(default_factory=dict)




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


def _complete(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` laid over the shipped ``config/default.toml`` (a MODEL.toml may be partial)."""
    from koala_bridge.core.resources import default_config_path
    from koala_bridge.runtime.settings import load_config

    return _laid_over(load_config(default_config_path()), config)


def check_config(config: Mapping[str, Any], where: str) -> None:
    """The same checks as ``koala-bridge run``: an unknown section or key, or a value of the
    wrong kind, is an error naming it (and the nearest valid name), not a key silently
    ignored. MODEL.toml may be partial: it is laid over the shipped ``config/default.toml``
    first, and the bridge's and the simulator's own loaders check the result."""
    from koala_bridge.core.schema import ConfigError
    from koala_bridge.runtime.localisation import LocalisationSettings
    from koala_bridge.runtime.settings import BridgeSettings, reject_unknown_sections

    if not config:
        return
    merged = _complete(config)
    try:
        reject_unknown_sections(merged)
        BridgeSettings.from_config(merged)
        _typed(config, where)
        LocalisationSettings.from_config(merged)
    except ConfigError as e:
        raise ModelConfigError(f"{where}: {e}") from e


def _typed(config: Mapping[str, Any], where: str = "model config") -> SimConfig | None:
    """The simulator's typed config of ``config`` (laid over default.toml); None for none."""
    from koala_bridge.core.schema import ConfigError
    from koala_bridge.sim.config import load_sim_config

    if not config:
        return None
    try:
        return load_sim_config(_complete(config))
    except ConfigError as e:
        raise ModelConfigError(f"{where}: {e}") from e


#: meta.json values that declare a config key (``meta path -> config dotted key``): where both
#: state one, meta.json wins (:func:`declared_model`).
META_KEYS: Mapping[tuple[str, ...], str] = {
    ("robot", "ticks_per_metre"): "robot.ticks_per_metre",
    ("robot", "wheel_base_m"): "robot.wheel_base_m",
    ("robot", "wheel_diameter_ratio"): "robot.wheel_diameter_ratio",
    ("sensor", "gyro", "bias_rad_s"): "sensors.gyro.bias_rad_s",
    ("sensor", "gyro", "scale_factor_error"): "sensors.gyro.scale_factor_error",
}


def meta_declared(meta: Mapping[str, Any]) -> dict[str, float]:
    """The config keys ``meta.json`` declares (:data:`META_KEYS`), with its values; a
    ``robot.tick_size_m`` (metres per tick) declares ``robot.ticks_per_metre`` as its inverse
    where ``robot.ticks_per_metre`` itself is not given."""
    out = {}
    for path, dotted in META_KEYS.items():
        value = _section(meta, *path[:-1]).get(path[-1])
        if isinstance(value, int | float) and not isinstance(value, bool):
            out[dotted] = float(value)
    size = _section(meta, "robot").get("tick_size_m")
    if "robot.ticks_per_metre" not in out and isinstance(size, int | float) and size > 0:
        out["robot.ticks_per_metre"] = 1.0 / float(size)
    return out


def stated_key(config: Mapping[str, Any], dotted: str) -> bool:
    """Whether ``config`` names the key ``a.b.c``."""
    *head, last = dotted.split(".")
    return last in _section(config, *head)


def config_value(config: Mapping[str, Any], dotted: str) -> Any:
    """The value ``config`` states for the key ``a.b.c`` (None when it states none)."""
    *head, last = dotted.split(".")
    return _section(config, *head).get(last)


def without_declared(meta: Mapping[str, Any], dotted: set[str] | frozenset[str]) -> dict[str, Any]:
    """``meta`` without the values of :data:`META_KEYS` whose config keys are in ``dotted``."""
    out = copy.deepcopy(dict(meta))
    for path, key in META_KEYS.items():
        node = _section(out, *path[:-1])
        if key in dotted and isinstance(node, dict):
            node.pop(path[-1], None)
            if key == "robot.ticks_per_metre":
                node.pop("tick_size_m", None)  # its other form (meta_declared)
    return out


def declared_model(config: Mapping[str, Any], meta: Mapping[str, Any]) -> DeclaredModel:
    """Combine the config with a bundle's ``meta.json`` (meta wins) into a DeclaredModel.

    Values come from the simulator's typed config (:func:`koala_bridge.sim.config.
    load_sim_config` of ``config`` laid over ``config/default.toml``): the same types, ranges
    and units as a run. Which effects are *declared* is what ``config`` states: an effect whose
    key the file does not name is absent (zero bias, unit gain, no table), so a partial
    MODEL.toml, or none, declares only what it says (the bundle format's precedence).
    """
    sources: dict[str, str] = {}
    typed = _typed(config)

    def stated(*path: str) -> bool:
        """Whether ``config`` names the key (or table) at ``path``."""
        return stated_key(config, ".".join(path))

    meta_robot = meta.get("robot", {}) if isinstance(meta.get("robot"), Mapping) else {}
    from_meta = meta_declared(meta)  # ticks_per_metre from tick_size_m too

    def pick(key: str) -> float | None:
        if f"robot.{key}" in from_meta:
            sources[key] = "meta.json robot"
            return from_meta[f"robot.{key}"]
        if typed is not None and stated("robot", key):
            sources[key] = "config [robot]"
            return float(getattr(typed.robot, key))
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

    meta_sensor = meta.get("sensor", {}) if isinstance(meta.get("sensor"), Mapping) else {}
    meta_gyro = meta_sensor.get("gyro") if isinstance(meta_sensor.get("gyro"), Mapping) else {}
    bias = scale = turn_on = 0.0
    interval = None
    if typed is not None:
        gyro = typed.sensors.gyro
        if not gyro.ideal:
            ge = gyro.errors
            bias = ge.bias_rad_s if stated("sensors", "gyro", "bias_rad_s") else 0.0
            scale = (ge.scale_factor_error
                     if stated("sensors", "gyro", "scale_factor_error") else 0.0)
            turn_on = (ge.turn_on_bias_sigma
                       if stated("sensors", "gyro", "turn_on_bias_sigma") else 0.0)
        if stated("sensors", "gyro", "rate_hz"):
            interval = 1.0 / gyro.rate_hz
    if isinstance(meta_gyro, Mapping):
        if isinstance(meta_gyro.get("bias_rad_s"), int | float):
            bias, turn_on = float(meta_gyro["bias_rad_s"]), 0.0
        if isinstance(meta_gyro.get("scale_factor_error"), int | float):
            scale = float(meta_gyro["scale_factor_error"])

    hard = (0.0, 0.0, 0.0)
    soft: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    motor = None
    world = None
    if typed is not None and not typed.sensors.compass.ideal:
        ce = typed.sensors.compass.errors
        if stated("sensors", "compass", "hard_iron_uT"):
            hard = tuple(float(v) for v in ce.hard_iron_uT)  # type: ignore[assignment]
        if stated("sensors", "compass", "soft_iron"):
            soft = tuple(tuple(float(v) for v in row) for row in ce.soft_iron)
        if stated("sensors", "compass", "motor_uT_per_A"):
            k = (ce.motor_current_A_per_mps
                 if stated("sensors", "compass", "motor_current_A_per_mps") else 0.0)
            m = np.asarray(ce.motor_uT_per_A, dtype=float)
            if np.any(m * k != 0):
                motor = tuple(tuple(float(v) for v in row) for row in m * k)
    if typed is not None:
        world = _world_field(typed, stated)

    curve = None
    gain = 1.0
    offsets: tuple[float, ...] = ()
    ir_count = None
    if typed is not None:
        ir = typed.sensors.ir
        if stated("sensors", "ir", "poses"):
            ir_count = int(ir.poses.shape[0])
        if stated("sensors", "ir") and not ir.ideal:
            ie = ir.errors
            if stated("sensors", "ir", "response_range_m") or stated(
                    "sensors", "ir", "response_counts"):
                curve = (tuple(float(v) for v in ir.response_range_m),
                         tuple(float(v) for v in ir.response_counts))
            # sim/models/ir.py: c = rho R(d) (1 - ambient_saturation A / max_counts) + o_s + noise
            refl = ie.reflectivity if stated("sensors", "ir", "reflectivity") else 1.0
            sat = ie.ambient_saturation if stated("sensors", "ir", "ambient_saturation") else 0.0
            amb = ir.ambient_counts if stated("sensors", "ir", "ambient_counts") else 0.0
            gain = refl * (1.0 - sat * min(amb, ir.max_counts) / ir.max_counts)
            offsets = tuple(float(v) for v in ie.per_sensor_offset_counts)
    critical = None
    sonar_range = None
    sonar_table = None
    sonar_glitch = 0.0
    if typed is not None and not typed.sensors.sonar.ideal:
        sonar = typed.sensors.sonar
        sonar_glitch = float(sonar.errors.glitch_probability)  # what the simulator draws
        if stated("sensors", "sonar", "critical_angle_deg"):
            critical = float(np.deg2rad(sonar.errors.critical_angle_deg))
        if stated("sensors", "sonar", "min_range_m") and stated("sensors", "sonar", "max_range_m"):
            sonar_range = (sonar.min_range_m, sonar.max_range_m)
            if stated("sensors", "sonar", "distance_error"):
                table = sonar.errors.distance_error
                sonar_table = (tuple(float(v) for v in table.x),
                               tuple(float(v) for v in table.y))
    wrong_ids, far, bearing_sigma = False, None, 0.0
    if typed is not None and stated("sensors", "camera") and not typed.sensors.camera.ideal:
        cam = typed.sensors.camera.errors
        wrong_ids = stated("sensors", "camera", "p_recog") and cam.p_recog > 0
        if all(stated("sensors", "camera", k) for k in ("dist", "d_mid_m", "far_doubling_m")):
            far = (cam.dist, cam.d_mid_m, cam.far_doubling_m)
        if stated("sensors", "camera", "bearing_sigma_deg"):
            bearing_sigma = float(np.deg2rad(cam.bearing_sigma_deg))
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
        ir_sensor_count=ir_count,
        sonar_critical_angle_rad=critical,
        sonar_range_m=sonar_range,
        sonar_distance_error=sonar_table,
        sonar_glitch_probability=sonar_glitch,
        camera_wrong_ids=wrong_ids,
        camera_far=far,
        camera_bearing_sigma_rad=bearing_sigma,
        sources=sources,
    )


def _world_field(typed: SimConfig, stated: Callable[..., bool]) -> WorldField | None:
    """The declared world's magnetic field (``[world.earth_field]``, ``[[world.magnetic_sources]]``)
    when the file states both and has local sources; None otherwise (a uniform field: north is a
    nuisance anyway)."""
    world = typed.world
    if not (stated("world", "magnetic_sources") and stated("world", "earth_field")
            and world.magnetic_sources):
        return None
    earth = world.earth_field
    h, north = earth.horizontal_uT, np.deg2rad(earth.north_deg)
    src = tuple((m.x, m.y, m.strength_uT) for m in world.magnetic_sources)
    dmin = typed.sensors.compass.min_source_distance_m
    return (float(h * np.cos(north)), float(h * np.sin(north)), earth.vertical_uT), src, dmin
