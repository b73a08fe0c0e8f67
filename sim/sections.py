"""What every typed section of the simulator's configuration shares: the split of a sensor's
table between the sensor's own keys and its error model's (:func:`sensor_section`), and the value
types of sensor tables (poses, response curves, ray counts).

The sections themselves live beside what they configure: each sensor's in
``sim/sensors/<name>.py`` (beside its truth), ``[robot]`` and ``[robot.drive_error]`` in
``sim/robot.py``; ``sim/config.py`` composes them into :class:`sim.config.SimConfig`. This module
imports no section (it sits below all of them), and the error models' params classes only
lazily, by name (:data:`ERROR_PARAMS`).

Units: SI unless the key's suffix says otherwise (``_deg``, ``_hz``, ``_uT``, ``_counts``).
Sensor poses are in the body frame FLU (x forward, y left), ``[x_m, y_m, theta_deg]`` with theta
counter-clockwise from the robot's forward axis.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Annotated, Any, TypeVar

import numpy as np
from koala_bridge.core.schema import (
    MAX_MAGNITUDE,
    ConfigError,
    PositiveInt,
    reject_unknown,
    validate,
)
from pydantic import AfterValidator, BeforeValidator

T = TypeVar("T")


def empty_errors() -> Mapping[str, Any]:
    """The ``errors`` of a section whose error model is off or absent: an empty mapping."""
    return MappingProxyType({})


# Error-model parameter classes (issue 3, owned by sim/models/), imported lazily by name so that
# no section module depends on them: module, class. Each is a core.schema section with
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


def error_params_class(model: str) -> Any | None:
    spec = ERROR_PARAMS.get(model)
    if spec is None:
        return None
    try:
        module = importlib.import_module(spec[0])
    except ModuleNotFoundError:
        return None
    return getattr(module, spec[1], None)


def own_keys(cls: Any) -> list[str]:
    """The file keys of a sensor section: its fields but ``errors`` (built, not read)."""
    return [f.name for f in dataclasses.fields(cls) if f.name != "errors"]


def _model_keys(sensor_keys: Sequence[str], model: str) -> list[str]:
    """The keys a section may hold: the sensor's own and its error model's (not FROM_SENSOR)."""
    cls = error_params_class(model)
    if cls is None:
        return list(sensor_keys)
    from_sensor = set(getattr(cls, "FROM_SENSOR", ()))
    return list(sensor_keys) + [f.name for f in dataclasses.fields(cls)
                                if f.name not in from_sensor and f.name not in sensor_keys]


def sensor_section(cls: type[T], d: Any, section: str, model: str) -> T:
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
    keys = own_keys(cls)
    reject_unknown(d, _model_keys(keys, model), section)
    own = {k: v for k, v in d.items() if k in keys}
    core = validate(cls, own, section)
    params_cls = error_params_class(model)
    if params_cls is None:
        return core
    rest: dict[str, Any] = {k: v for k, v in d.items() if k not in keys}
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


Poses = Annotated[np.ndarray, BeforeValidator(_poses)]
Pose = Annotated[tuple[float, float, float], BeforeValidator(_pose)]
Curve = Annotated[np.ndarray, BeforeValidator(_curve)]
Rays = Annotated[PositiveInt, AfterValidator(_odd)]


def range_limits(lo: float, hi: float, section: str) -> None:
    if lo >= hi:
        raise ConfigError(f"[{section}] 'min_range_m' must be < 'max_range_m'")



def poses_to_list(poses: np.ndarray | Sequence[Sequence[float]]) -> list[dict[str, float]]:
    """Body-frame poses as JSON-ready dicts ``{x, y, theta}`` (metres, radians)."""
    return [{"x": float(p[0]), "y": float(p[1]), "theta": float(p[2])} for p in poses]
