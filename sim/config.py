"""Typed, frozen simulator configuration: ``[sim]``, ``[robot]``, ``[sensors.*]``, ``[world]``.

Built from plain dicts (the parsed TOML; file I/O lives in ``bridge/``) by :func:`load_sim_config`.
Every section is a :func:`koala_bridge.core.schema.section`, so the schema's one policy applies
(config/README.md "Policy"): every key these sections own is *required* and written in
``config/default.toml``; types are strict; numbers finite and in range; unknown keys are
:class:`koala_bridge.core.schema.ConfigError` that suggest the nearest valid key. Error-model
parameters are validated by their own params classes, whose defaults are default.toml's values.
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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Annotated, Any, TypeVar

import numpy as np
from koala_bridge.core.schema import (
    MAX_MAGNITUDE,
    Bool,
    ConfigError,
    Finite,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    Str,
    reject_unknown,
    require,
    section,
    validate,
)
from koala_bridge.sim.world import World
from pydantic import AfterValidator, BeforeValidator, Field, Strict

T = TypeVar("T")

# The sensors of the simulated Koala, in the FIXED order used to spawn their RNG streams
# (sim.simulator.RNG_STREAMS appends "drive" first). Append new sensors at the end only.
SENSOR_NAMES = ("ir", "sonar", "encoders", "gyro", "compass", "camera")

def _empty() -> Mapping[str, Any]:
    return MappingProxyType({})


# Error-model parameter classes (issue 3, owned by sim/models/), imported lazily by name so that
# sim/config.py does not depend on them: module, class. Each is a core.schema section with
# ``from_dict(d, section)`` and a ``FROM_SENSOR`` tuple of the fields it reads from the sensor's
# own keys. The encoders have none.
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


def _own_keys(cls: Any) -> list[str]:
    """The file keys of a sensor section: its fields but ``errors`` (built, not read)."""
    return [f.name for f in dataclasses.fields(cls) if f.name != "errors"]


def _model_keys(own_keys: Sequence[str], model: str) -> list[str]:
    """The keys a section may hold: the sensor's own and its error model's (not FROM_SENSOR)."""
    cls = _error_params_class(model)
    if cls is None:
        return list(own_keys)
    from_sensor = set(getattr(cls, "FROM_SENSOR", ()))
    return list(own_keys) + [f.name for f in dataclasses.fields(cls)
                             if f.name not in from_sensor and f.name not in own_keys]


def _sensor_section(cls: type[T], d: Any, section: str, model: str) -> T:
    """Validate a table that mixes a sensor's keys with its error model's keys.

    A section such as ``[sensors.gyro]`` holds the simulator's keys (``rate_hz``, ``ideal``, ...)
    *and* the parameters of the sensor's error model (issue 3), side by side. Each key has one
    owner: the sensor's fields (``cls``) are validated here; the others go to the error model's
    params class (:data:`ERROR_PARAMS`). A value both need (``ideal``, ``min_range_m``, ...) is
    owned by the sensor: the params class lists it in ``FROM_SENSOR`` and receives the sensor's
    already validated value. A key known to neither is an error suggesting the nearest valid
    key (checked first, before any missing-key error). The result's ``errors`` is the params
    object (an empty mapping when no error model exists for this sensor).
    """
    if not isinstance(d, Mapping):
        raise ConfigError(f"[{section}] must be a table, got {d!r}")
    own_keys = _own_keys(cls)
    reject_unknown(d, _model_keys(own_keys, model), section)
    own = {k: v for k, v in d.items() if k in own_keys}
    core = validate(cls, own, section)
    params_cls = _error_params_class(model)
    if params_cls is None:
        return core
    rest: dict[str, Any] = {k: v for k, v in d.items() if k not in own_keys}
    rest.update({k: getattr(core, k) for k in getattr(params_cls, "FROM_SENSOR", ())})
    errors = params_cls.from_dict(rest, section)
    # Built again with the params: checks across both (IR offsets per sensor) run in one place.
    return validate(cls, {**own, "errors": errors}, section)


def _numbers(value: Any) -> bool:
    """A (nested) TOML array of numbers only (no strings, no booleans)."""
    if isinstance(value, np.ndarray):
        return True
    if isinstance(value, list | tuple):
        return all(_numbers(v) for v in value)
    return isinstance(value, int | float) and not isinstance(value, bool)


def _poses(value: Any) -> np.ndarray:
    """``[[x_m, y_m, theta_deg], ...]`` -> read-only ``(n, 3)`` array ``[x, y, theta_rad]``."""
    if isinstance(value, np.ndarray) and not value.flags.writeable:
        return value  # already converted (a section built from another's fields)
    wrong = "must be a non-empty list of [x_m, y_m, theta_deg]"
    if not _numbers(value):
        raise ValueError(f"{wrong}, got {value!r}")
    arr = np.array(value, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0 or not np.all(np.isfinite(arr)):
        raise ValueError(f"{wrong}, got {value!r}")
    if np.any(np.abs(arr) > MAX_MAGNITUDE):
        raise ValueError(f"{wrong} with plausible numbers, got {value!r}")
    arr[:, 2] = np.radians(arr[:, 2])
    arr.flags.writeable = False
    return arr


def _pose(value: Any) -> tuple[float, float, float]:
    p = _poses([list(value)] if isinstance(value, list | tuple) else value)[0]
    return (float(p[0]), float(p[1]), float(p[2]))


def _curve(value: Any) -> np.ndarray:
    """A 1-d read-only array of finite numbers (a response table column)."""
    if isinstance(value, np.ndarray) and not value.flags.writeable:
        return value
    if not isinstance(value, list | tuple) or not _numbers(value):
        raise ValueError(f"must be a list of numbers, got {value!r}")
    arr = np.array(value, dtype=float)
    if arr.ndim != 1 or not np.all(np.isfinite(arr)) or np.any(np.abs(arr) > MAX_MAGNITUDE):
        raise ValueError(f"must be a flat list of finite numbers, got {value!r}")
    arr.flags.writeable = False
    return arr


def _odd(n: int) -> int:
    if n % 2 == 0:
        raise ValueError(f"must be odd (one ray on the sensor's axis), got {n}")
    return n


def _key_safe(name: str) -> str:
    if not name or any(c in name for c in "/*?$# "):
        raise ValueError(f"must be a non-empty key-safe word, got {name!r}")
    return name


Poses = Annotated[np.ndarray, BeforeValidator(_poses)]
Pose = Annotated[tuple[float, float, float], BeforeValidator(_pose)]
Curve = Annotated[np.ndarray, BeforeValidator(_curve)]
Rays = Annotated[PositiveInt, AfterValidator(_odd)]
#: ``[sim] dt_s`` bounds: 0.1 ms .. 1 s. A smaller step would take hours for a second of
#: simulated time (1e-9 would hang a run); a larger one is no longer a controller period.
STEP_LIMITS_S = (1e-4, 1.0)


def _range_limits(lo: float, hi: float, section: str) -> None:
    if lo >= hi:
        raise ConfigError(f"[{section}] 'min_range_m' must be < 'max_range_m'")


# ------------------------------------------------------------------------------ sections


@section
class StepConfig:
    """``[sim]``: the fixed integration step and the default seed."""

    dt_s: Annotated[Finite, Field(ge=STEP_LIMITS_S[0], le=STEP_LIMITS_S[1])]
    seed: Annotated[int, Strict(), Field(ge=0)]

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StepConfig:
        return validate(cls, d, "sim")


@section
class DriveConfig:
    """``[robot.drive_error]``: the drive-error model's switch and parameters (seeds/000 1-4)."""

    ideal: Bool
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DriveConfig:
        return _sensor_section(cls, d, "robot.drive_error", "drive")


@section
class RobotConfig:
    """``[robot]``: geometry and drive limits of the Koala (sources in config/README.md)."""

    name: Annotated[Str, AfterValidator(_key_safe)]
    ticks_per_metre: Positive       # encoder pulses per metre of wheel travel
    wheel_diameter_m: Positive
    wheel_base_m: Positive          # distance between the left and right wheel contact lines
    wheel_diameter_ratio: Positive  # left / right wheel diameter (1: equal); see sim/robot.py
    body_radius_m: Positive         # collision body: a circle around the robot's centre
    max_wheel_speed_mps: Positive   # wheel surface speed limit, each wheel
    speed_unit_s: Positive          # K-Team speed unit = pulses per this many seconds (10 ms)
    drive: DriveConfig              # the file's [robot.drive_error] table

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RobotConfig:
        sec = "robot"
        if not isinstance(d, Mapping):
            raise ConfigError(f"[{sec}] must be a table, got {d!r}")
        keys = [k for k in _own_keys(cls) if k != "drive"] + ["drive_error"]
        reject_unknown(d, keys, sec)
        own = {k: v for k, v in d.items() if k != "drive_error"}
        drive = DriveConfig.from_dict(require(d, "drive_error", sec))
        return validate(cls, {**own, "drive": drive}, sec)


@section(eq=False)
class IrConfig:
    """``[sensors.ir]``: proximity sensors, K-Team counts from a response table range -> counts."""

    rate_hz: Positive
    ideal: Bool
    poses: Poses                        # (n, 3) body frame [x, y, theta_rad]
    rays: Rays                          # rays per sensor, spread over the aperture
    aperture_deg: NonNegative
    response_range_m: Curve             # (k,) increasing
    response_counts: Curve              # (k,) counts at those ranges (linear interpolation)
    ambient_counts: NonNegativeInt      # ambient light reading (K-Team 'O')
    max_counts: PositiveInt             # full scale of the counts (K-Team: 10 bits, 1023)
    errors: Any = field(default_factory=_empty)

    def __post_init__(self) -> None:
        sec = "sensors.ir"
        rng_m, counts, full = self.response_range_m, self.response_counts, self.max_counts
        if rng_m.shape != counts.shape or rng_m.size < 2:
            raise ConfigError(
                f"[{sec}] 'response_range_m' and 'response_counts' must be lists of equal "
                "length >= 2"
            )
        if np.any(np.diff(rng_m) <= 0) or rng_m[0] < 0:
            raise ConfigError(f"[{sec}] 'response_range_m' must be >= 0 and strictly increasing")
        if np.any(counts < 0) or np.any(counts > full):
            raise ConfigError(f"[{sec}] 'response_counts' must lie in 0..max_counts ({full})")
        if self.ambient_counts > full:
            raise ConfigError(
                f"[{sec}] 'ambient_counts' must lie in 0..max_counts ({full}), "
                f"got {self.ambient_counts}")
        offsets = getattr(self.errors, "per_sensor_offset_counts", ())
        if len(offsets) not in (0, self.poses.shape[0]):
            raise ConfigError(
                f"[{sec}] 'per_sensor_offset_counts' must be [] or one value per sensor "
                f"({self.poses.shape[0]}), got {len(offsets)}"
            )

    @property
    def max_range_m(self) -> float:
        return float(self.response_range_m[-1])

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> IrConfig:
        return _sensor_section(cls, d, "sensors.ir", "ir")


@section(eq=False)
class SonarConfig:
    """``[sensors.sonar]``: ultrasonic ring, each sensor a cone of rays; first echo wins."""

    rate_hz: Positive
    ideal: Bool
    poses: Poses                        # (n, 3) body frame [x, y, theta_rad]
    rays: Rays
    aperture_deg: NonNegative
    min_range_m: NonNegative            # closer: the Koala reports 0
    max_range_m: Positive               # farther: no echo
    errors: Any = field(default_factory=_empty)

    def __post_init__(self) -> None:
        _range_limits(self.min_range_m, self.max_range_m, "sensors.sonar")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SonarConfig:
        return _sensor_section(cls, d, "sensors.sonar", "sonar")


@section
class BasicSensorConfig:
    """``[sensors.encoders]``, ``[sensors.gyro]``: a rate and the ideal switch."""

    rate_hz: Positive
    ideal: Bool
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], sec: str, model: str) -> BasicSensorConfig:
        out = _sensor_section(cls, d, sec, model)
        if not out.ideal and _error_params_class(model) is None:
            raise ConfigError(
                f"[{sec}] 'ideal' must be true: the {model} have no error model of their own "
                "(their errors come from [robot.drive_error]: the counts are whole ticks of the "
                "commanded wheel rotation, from which the truth pose drifts); see "
                "config/README.md"
            )
        return out


@section
class CompassConfig:
    """``[sensors.compass]``: 3-axis magnetometer, Earth field plus local sources (1/d^2)."""

    rate_hz: Positive
    ideal: Bool
    min_source_distance_m: Positive     # 1/d^2 is clamped at this distance (no singularity)
    errors: Any = field(default_factory=_empty)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CompassConfig:
        return _sensor_section(cls, d, "sensors.compass", "compass")


@section
class CameraConfig:
    """``[sensors.camera]``: landmark observations within a field of view and line of sight."""

    rate_hz: Positive
    ideal: Bool
    pose: Pose                          # body frame [x, y, theta_rad]
    fov_deg: Annotated[Positive, Field(le=360)]   # full horizontal field of view
    min_range_m: NonNegative
    max_range_m: Positive
    errors: Any = field(default_factory=_empty)

    def __post_init__(self) -> None:
        _range_limits(self.min_range_m, self.max_range_m, "sensors.camera")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraConfig:
        return _sensor_section(cls, d, "sensors.camera", "camera")


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
