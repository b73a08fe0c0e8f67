"""Typed, frozen simulator configuration: ``[sim]``, ``[robot]``, ``[sensors.*]``, ``[world]``.

Built from plain dicts (the parsed TOML; file I/O lives in ``bridge/``) by :func:`load_sim_config`.
Every key a run uses is written in ``config/default.toml``; nothing here hides a default that the
file should show, so every key of these sections is *required* (error-model parameters are
validated by their own classes). Unknown keys are :class:`koala_bridge.core.schema.ConfigError` that
suggest the nearest valid key.
Top-level sections other than ``sim``, ``robot``, ``sensors`` and ``world`` belong to ``bridge/``
and are ignored here.

Units: SI unless the key's suffix says otherwise (``_deg``, ``_hz``, ``_uT``, ``_counts``).
Sensor poses are in the body frame FLU (x forward, y left), ``[x_m, y_m, theta_deg]`` with theta
counter-clockwise from the robot's forward axis.

Seam for error models (issue 3): every sensor section and ``[robot.drive_error]`` has ``ideal``
(bool) and, side by side with the simulator's keys, the parameters of that sensor's error model
(``[sensors.gyro] gyroscope_noise_density = ...``). The error model's params class
(:data:`ERROR_PARAMS`, in ``sim/models/``, imported lazily) validates and types them; the result is
the sensor config's ``errors`` attribute. A value both need (``ideal``, ``min_range_m``, ...) has
one key, owned and validated here and handed to the params class (its ``FROM_SENSOR`` fields).
With ``ideal = true`` the sensor reports its noise-free value whatever those parameters say. The
encoders have no error model: ``[sensors.encoders] ideal = false`` is a config error.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from koala_bridge.core.schema import ConfigError, positive, reject_unknown, require
from koala_bridge.sim.world import World

# The sensors of the simulated Koala, in the FIXED order used to spawn their RNG streams
# (sim.simulator.RNG_STREAMS appends "drive" first). Append new sensors at the end only.
SENSOR_NAMES = ("ir", "sonar", "encoders", "gyro", "compass", "camera")

def _empty() -> Mapping[str, Any]:
    return MappingProxyType({})


def _float(d: Mapping[str, Any], key: str, section: str) -> float:
    v = require(d, key, section)
    try:
        f = float(v)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{section}] '{key}' must be a number, got {v!r}") from e
    if not math.isfinite(f):
        raise ConfigError(f"[{section}] '{key}' must be finite, got {v!r}")
    return f


def _nonneg(d: Mapping[str, Any], key: str, section: str) -> float:
    f = _float(d, key, section)
    if f < 0:
        raise ConfigError(f"[{section}] '{key}' must be >= 0, got {f!r}")
    return f


def _bool(d: Mapping[str, Any], key: str, section: str) -> bool:
    v = require(d, key, section)
    if not isinstance(v, bool):
        raise ConfigError(f"[{section}] '{key}' must be true or false, got {v!r}")
    return v


def _int(d: Mapping[str, Any], key: str, section: str, minimum: int = 1) -> int:
    v = require(d, key, section)
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ConfigError(f"[{section}] '{key}' must be an integer >= {minimum}, got {v!r}")
    return v


def _odd(d: Mapping[str, Any], key: str, section: str) -> int:
    n = _int(d, key, section)
    if n % 2 == 0:
        raise ConfigError(
            f"[{section}] '{key}' must be odd (one ray on the sensor's axis), got {n}"
        )
    return n


# Error-model parameter classes (issue 3, owned by sim/models/), imported lazily by name so that
# sim/config.py does not depend on them: module, class. Each has ``from_dict(d, section)`` and a
# ``FROM_SENSOR`` tuple of the fields it reads from the sensor's own keys. The encoders have none.
ERROR_PARAMS: Mapping[str, tuple[str, str]] = MappingProxyType({
    "drive": ("koala_bridge.sim.models.drive", "DriveErrorParams"),
    "ir": ("koala_bridge.sim.models.ir", "IrErrorParams"),
    "sonar": ("koala_bridge.sim.models.sonar", "SonarErrorParams"),
    "gyro": ("koala_bridge.sim.models.gyro", "GyroErrorParams"),
    "compass": ("koala_bridge.sim.models.compass", "CompassErrorParams"),
    "camera": ("koala_bridge.sim.models.camera", "CameraErrorParams"),
})


def _error_params_class(model: str) -> Any | None:
    spec = ERROR_PARAMS.get(model)
    if spec is None:
        return None
    try:
        module = importlib.import_module(spec[0])
    except ModuleNotFoundError:
        return None
    return getattr(module, spec[1], None)


def _model_keys(own_keys: Sequence[str], model: str) -> list[str]:
    """The keys a section may hold: the sensor's own and its error model's (not FROM_SENSOR)."""
    cls = _error_params_class(model)
    if cls is None:
        return list(own_keys)
    from_sensor = set(getattr(cls, "FROM_SENSOR", ()))
    return list(own_keys) + [f.name for f in dataclasses.fields(cls)
                             if f.name not in from_sensor and f.name not in own_keys]


def _check_keys(d: Mapping[str, Any], own_keys: Sequence[str], section: str, model: str) -> None:
    """Unknown keys first (suggesting the nearest valid one), before any missing-key error."""
    reject_unknown(d, _model_keys(own_keys, model), section)


def _split_errors(
    d: Mapping[str, Any],
    own_keys: Sequence[str],
    section: str,
    model: str,
    shared: Mapping[str, Any],
) -> Any:
    """Validate a section that mixes this module's keys with an error model's keys.

    A section such as ``[sensors.gyro]`` holds the simulator's keys (``rate_hz``, ``ideal``, ...)
    *and* the parameters of the sensor's error model (issue 3), side by side. Each key has one
    owner: keys in ``own_keys`` belong to the sensor (validated here); the others go to the error
    model's params class (:data:`ERROR_PARAMS`). A value both need (``ideal``, ``min_range_m``,
    ...) is owned by the sensor: the params class lists it in ``FROM_SENSOR`` and receives the
    sensor's already validated value from ``shared``. A key known to neither is an error
    suggesting the nearest valid key. Returns the params object (an empty mapping when no error
    model exists for this sensor).
    """
    _check_keys(d, own_keys, section, model)
    cls = _error_params_class(model)
    if cls is None:
        return _empty()
    rest: dict[str, Any] = {k: v for k, v in d.items() if k not in own_keys}
    rest.update({k: shared[k] for k in getattr(cls, "FROM_SENSOR", ())})
    return cls.from_dict(rest, section)


def _range_limits(d: Mapping[str, Any], section: str) -> tuple[float, float]:
    """``(min_range_m, max_range_m)``: the first >= 0, the second > 0 and above the first."""
    lo = _nonneg(d, "min_range_m", section)
    hi = positive(require(d, "max_range_m", section), "max_range_m", section)
    if lo >= hi:
        raise ConfigError(f"[{section}] 'min_range_m' must be < 'max_range_m'")
    return lo, hi


def _poses(value: Any, key: str, section: str) -> np.ndarray:
    """``[[x_m, y_m, theta_deg], ...]`` -> read-only ``(n, 3)`` array ``[x, y, theta_rad]``."""
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{section}] '{key}' must be a list of [x_m, y_m, theta_deg]") from e
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0 or not np.all(np.isfinite(arr)):
        raise ConfigError(f"[{section}] '{key}' must be a non-empty list of [x_m, y_m, theta_deg]")
    arr[:, 2] = np.radians(arr[:, 2])
    arr.flags.writeable = False
    return arr


def _pose(value: Any, key: str, section: str) -> tuple[float, float, float]:
    p = _poses([value], key, section)[0]
    return (float(p[0]), float(p[1]), float(p[2]))


# ------------------------------------------------------------------------------ sections


@dataclass(frozen=True)
class StepConfig:
    """``[sim]``: the fixed integration step and the default seed."""

    dt_s: float
    seed: int

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StepConfig:
        sec = "sim"
        reject_unknown(d, ["dt_s", "seed"], sec)
        seed = require(d, "seed", sec)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"[sim] 'seed' must be a non-negative integer, got {seed!r}")
        return cls(dt_s=positive(require(d, "dt_s", sec), "dt_s", sec), seed=seed)


@dataclass(frozen=True)
class DriveConfig:
    """``[robot.drive]``: switch and parameters of the drive-error model (seeds/000 eq. 1-4)."""

    ideal: bool
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DriveConfig:
        sec = "robot.drive_error"
        _check_keys(d, ["ideal"], sec, "drive")
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(d, ["ideal"], sec, "drive", {"ideal": ideal})
        return cls(ideal=ideal, errors=errors)


@dataclass(frozen=True)
class RobotConfig:
    """``[robot]``: geometry and drive limits of the Koala (sources in config/README.md)."""

    name: str
    ticks_per_metre: float          # encoder pulses per metre of wheel travel
    wheel_diameter_m: float
    wheel_base_m: float             # distance between the left and right wheel contact lines
    wheel_diameter_ratio: float     # left / right wheel diameter (1: equal); see sim/robot.py
    body_radius_m: float            # collision body: a circle around the robot's centre
    max_wheel_speed_mps: float      # wheel surface speed limit, each wheel
    speed_unit_s: float             # K-Team speed unit = pulses per this many seconds (10 ms)
    drive: DriveConfig

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotConfig:
        sec = "robot"
        reject_unknown(
            d,
            ["name", "ticks_per_metre", "wheel_diameter_m", "wheel_base_m",
             "wheel_diameter_ratio", "body_radius_m", "max_wheel_speed_mps", "speed_unit_s",
             "drive_error"],
            sec,
        )
        name = str(require(d, "name", sec))
        if not name or any(c in name for c in "/*?$# "):
            raise ConfigError(f"[robot] 'name' must be a non-empty key-safe word, got {name!r}")
        return cls(
            name=name,
            ticks_per_metre=positive(require(d, "ticks_per_metre", sec), "ticks_per_metre", sec),
            wheel_diameter_m=positive(require(d, "wheel_diameter_m", sec), "wheel_diameter_m", sec),
            wheel_base_m=positive(require(d, "wheel_base_m", sec), "wheel_base_m", sec),
            wheel_diameter_ratio=positive(
                require(d, "wheel_diameter_ratio", sec), "wheel_diameter_ratio", sec
            ),
            body_radius_m=positive(require(d, "body_radius_m", sec), "body_radius_m", sec),
            max_wheel_speed_mps=positive(
                require(d, "max_wheel_speed_mps", sec), "max_wheel_speed_mps", sec
            ),
            speed_unit_s=positive(require(d, "speed_unit_s", sec), "speed_unit_s", sec),
            drive=DriveConfig.from_dict(require(d, "drive_error", sec)),
        )


@dataclass(frozen=True, eq=False)
class IrConfig:
    """``[sensors.ir]``: proximity sensors, K-Team counts from a response table range -> counts."""

    rate_hz: float
    ideal: bool
    poses: np.ndarray                   # (n, 3) body frame [x, y, theta_rad]
    rays: int                           # rays per sensor, spread over the aperture
    aperture_deg: float
    response_range_m: np.ndarray        # (k,) increasing
    response_counts: np.ndarray         # (k,) counts at those ranges (linear interpolation)
    ambient_counts: int                 # ambient light reading (K-Team 'O')
    max_counts: int                     # full scale of the counts (K-Team: 10 bits, 1023)
    errors: Any = field(default_factory=_empty)

    @property
    def max_range_m(self) -> float:
        return float(self.response_range_m[-1])

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IrConfig:
        sec = "sensors.ir"
        own = ["rate_hz", "ideal", "poses", "rays", "aperture_deg", "response_range_m",
               "response_counts", "ambient_counts", "max_counts"]
        _check_keys(d, own, sec, "ir")
        rng_m = np.array(require(d, "response_range_m", sec), dtype=float)
        counts = np.array(require(d, "response_counts", sec), dtype=float)
        if rng_m.ndim != 1 or rng_m.shape != counts.shape or rng_m.size < 2:
            raise ConfigError(
                f"[{sec}] 'response_range_m' and 'response_counts' must be lists of equal "
                "length >= 2"
            )
        if np.any(np.diff(rng_m) <= 0) or rng_m[0] < 0:
            raise ConfigError(f"[{sec}] 'response_range_m' must be >= 0 and strictly increasing")
        full = _int(d, "max_counts", sec)
        if np.any(counts < 0) or np.any(counts > full):
            raise ConfigError(f"[{sec}] 'response_counts' must lie in 0..max_counts ({full})")
        ambient = _int(d, "ambient_counts", sec, minimum=0)
        if ambient > full:
            raise ConfigError(
                f"[{sec}] 'ambient_counts' must lie in 0..max_counts ({full}), got {ambient}")
        for a in (rng_m, counts):
            a.flags.writeable = False
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(d, own, sec, "ir", {"ideal": ideal, "ambient_counts": ambient,
                                                   "max_counts": full})
        poses = _poses(require(d, "poses", sec), "poses", sec)
        offsets = getattr(errors, "per_sensor_offset_counts", ())
        if len(offsets) not in (0, poses.shape[0]):
            raise ConfigError(
                f"[{sec}] 'per_sensor_offset_counts' must be [] or one value per sensor "
                f"({poses.shape[0]}), got {len(offsets)}"
            )
        return cls(
            rate_hz=positive(require(d, "rate_hz", sec), "rate_hz", sec),
            ideal=ideal,
            poses=poses,
            rays=_odd(d, "rays", sec),
            aperture_deg=_nonneg(d, "aperture_deg", sec),
            response_range_m=rng_m,
            response_counts=counts,
            ambient_counts=ambient,
            max_counts=full,
            errors=errors,
        )


@dataclass(frozen=True, eq=False)
class SonarConfig:
    """``[sensors.sonar]``: ultrasonic ring, each sensor a cone of rays; first echo wins."""

    rate_hz: float
    ideal: bool
    poses: np.ndarray                   # (n, 3) body frame [x, y, theta_rad]
    rays: int
    aperture_deg: float
    min_range_m: float                  # closer: the Koala reports 0
    max_range_m: float                  # farther: no echo
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SonarConfig:
        sec = "sensors.sonar"
        own = ["rate_hz", "ideal", "poses", "rays", "aperture_deg", "min_range_m", "max_range_m"]
        _check_keys(d, own, sec, "sonar")
        lo, hi = _range_limits(d, sec)
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(
            d, own, sec, "sonar", {"ideal": ideal, "min_range_m": lo, "max_range_m": hi}
        )
        return cls(
            rate_hz=positive(require(d, "rate_hz", sec), "rate_hz", sec),
            ideal=ideal,
            poses=_poses(require(d, "poses", sec), "poses", sec),
            rays=_odd(d, "rays", sec),
            aperture_deg=_nonneg(d, "aperture_deg", sec),
            min_range_m=lo,
            max_range_m=hi,
            errors=errors,
        )


@dataclass(frozen=True)
class BasicSensorConfig:
    """``[sensors.encoders]``, ``[sensors.gyro]``: a rate and the ideal switch."""

    rate_hz: float
    ideal: bool
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], sec: str, model: str) -> BasicSensorConfig:
        own = ["rate_hz", "ideal"]
        _check_keys(d, own, sec, model)
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(d, own, sec, model, {"ideal": ideal})
        if not ideal and _error_params_class(model) is None:
            raise ConfigError(
                f"[{sec}] 'ideal' must be true: the {model} have no error model of their own "
                "(their errors come from [robot.drive_error]: the counts are whole ticks of the "
                "commanded wheel rotation, from which the truth pose drifts); see "
                "config/README.md"
            )
        return cls(
            rate_hz=positive(require(d, "rate_hz", sec), "rate_hz", sec),
            ideal=ideal,
            errors=errors,
        )


@dataclass(frozen=True)
class CompassConfig:
    """``[sensors.compass]``: 3-axis magnetometer, Earth field plus local sources (1/d^2)."""

    rate_hz: float
    ideal: bool
    min_source_distance_m: float        # 1/d^2 is clamped at this distance (no singularity)
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CompassConfig:
        sec = "sensors.compass"
        own = ["rate_hz", "ideal", "min_source_distance_m"]
        _check_keys(d, own, sec, "compass")
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(d, own, sec, "compass", {"ideal": ideal})
        return cls(
            rate_hz=positive(require(d, "rate_hz", sec), "rate_hz", sec),
            ideal=ideal,
            min_source_distance_m=positive(
                require(d, "min_source_distance_m", sec), "min_source_distance_m", sec
            ),
            errors=errors,
        )


@dataclass(frozen=True)
class CameraConfig:
    """``[sensors.camera]``: landmark observations within a field of view and line of sight."""

    rate_hz: float
    ideal: bool
    pose: tuple[float, float, float]    # body frame [x, y, theta_rad]
    fov_deg: float                      # full horizontal field of view
    min_range_m: float
    max_range_m: float
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraConfig:
        sec = "sensors.camera"
        own = ["rate_hz", "ideal", "pose", "fov_deg", "min_range_m", "max_range_m"]
        _check_keys(d, own, sec, "camera")
        lo, hi = _range_limits(d, sec)
        ideal = _bool(d, "ideal", sec)
        errors = _split_errors(
            d, own, sec, "camera", {"ideal": ideal, "min_range_m": lo, "max_range_m": hi}
        )
        fov = positive(require(d, "fov_deg", sec), "fov_deg", sec)
        if fov > 360:
            raise ConfigError(f"[{sec}] 'fov_deg' must be <= 360, got {fov}")
        return cls(
            rate_hz=positive(require(d, "rate_hz", sec), "rate_hz", sec),
            ideal=ideal,
            pose=_pose(require(d, "pose", sec), "pose", sec),
            fov_deg=fov,
            min_range_m=lo,
            max_range_m=hi,
            errors=errors,
        )


@dataclass(frozen=True)
class SensorsConfig:
    """``[sensors]``: one table per sensor of :data:`SENSOR_NAMES`."""

    ir: IrConfig
    sonar: SonarConfig
    encoders: BasicSensorConfig
    gyro: BasicSensorConfig
    compass: CompassConfig
    camera: CameraConfig

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SensorsConfig:
        reject_unknown(d, SENSOR_NAMES, "sensors")
        for name in SENSOR_NAMES:
            require(d, name, "sensors")
        return cls(
            ir=IrConfig.from_dict(d["ir"]),
            sonar=SonarConfig.from_dict(d["sonar"]),
            encoders=BasicSensorConfig.from_dict(d["encoders"], "sensors.encoders", "encoders"),
            gyro=BasicSensorConfig.from_dict(d["gyro"], "sensors.gyro", "gyro"),
            compass=CompassConfig.from_dict(d["compass"]),
            camera=CameraConfig.from_dict(d["camera"]),
        )

    def rates_hz(self) -> dict[str, float]:
        return {name: getattr(self, name).rate_hz for name in SENSOR_NAMES}


@dataclass(frozen=True)
class SimConfig:
    """Everything :class:`sim.simulator.Simulator` needs: step, robot, sensors and world."""

    sim: StepConfig
    robot: RobotConfig
    sensors: SensorsConfig
    world: World

    def period_steps(self, rate_hz: float) -> int:
        """Steps between two samples of a sensor at ``rate_hz`` (exact multiple of ``dt``)."""
        return _period_steps(rate_hz, self.sim.dt_s)


def _period_steps(rate_hz: float, dt_s: float) -> int:
    n = 1.0 / (rate_hz * dt_s)
    k = round(n)
    if k < 1 or abs(n - k) > 1e-6 * max(1.0, n):
        raise ConfigError(
            f"a sensor rate of {rate_hz} Hz is not a whole number of {dt_s} s steps "
            f"(1 / (rate * dt) = {n:.6g}); choose a rate that divides 1/dt = {1 / dt_s:.6g} Hz"
        )
    return int(k)


def load_sim_config(d: Mapping[str, Any]) -> SimConfig:
    """Build a :class:`SimConfig` from a parsed config file (``tomllib.load`` output).

    Reads ``[sim]``, ``[robot]``, ``[sensors.*]`` and ``[world]``; other top-level tables are the
    bridge's and are ignored. Raises :class:`core.schema.ConfigError` naming section and key.
    """
    for key in ("sim", "robot", "sensors", "world"):
        require(d, key, "<top level>")
    step = StepConfig.from_dict(d["sim"])
    sensors = SensorsConfig.from_dict(d["sensors"])
    for name, rate in sensors.rates_hz().items():
        try:
            _period_steps(rate, step.dt_s)
        except ConfigError as e:
            raise ConfigError(f"[sensors.{name}] 'rate_hz': {e}") from None
    return SimConfig(
        sim=step,
        robot=RobotConfig.from_dict(d["robot"]),
        sensors=sensors,
        world=World.from_dict(d["world"]),
    )


def poses_to_list(poses: np.ndarray | Sequence[Sequence[float]]) -> list[dict[str, float]]:
    """Body-frame poses as JSON-ready dicts ``{x, y, theta}`` (metres, radians)."""
    return [{"x": float(p[0]), "y": float(p[1]), "theta": float(p[2])} for p in poses]
