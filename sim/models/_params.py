"""Build a frozen params dataclass from a config table: unknown keys suggest the nearest key."""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from koala_bridge.core.schema import ConfigError, reject_unknown
from koala_bridge.sim.noise import LookupTable

T = TypeVar("T")


def params_from_dict(cls: type[T], d: Mapping[str, Any], section: str) -> T:
    """Convert ``d`` into ``cls`` field by field, following the field annotations.

    ``float`` and ``int`` fields take numbers (``inf`` allowed where the class permits it),
    ``bool`` fields take booleans only, ``LookupTable`` fields take ``[[x, y, noise], ...]`` rows,
    ``tuple`` fields take (nested) number arrays. Missing keys keep the dataclass default.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    reject_unknown(d, fields, section)
    hints = typing.get_type_hints(cls)
    kw: dict[str, Any] = {}
    for key, value in d.items():
        kw[key] = _convert(value, hints[key], f"{section}.{key}")
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{section}] {e}") from e


def _convert(value: Any, hint: Any, where: str) -> Any:
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"[{where}] must be true or false, got {value!r}")
        return value
    if hint is float:
        try:
            v = float(value)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"[{where}] must be a number, got {value!r}") from e
        if math.isnan(v):
            raise ConfigError(f"[{where}] must not be nan")
        return v
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int | float) or int(value) != value:
            raise ConfigError(f"[{where}] must be an integer, got {value!r}")
        return int(value)
    if hint is LookupTable:
        return LookupTable.from_rows(value, where)
    origin = typing.get_origin(hint)
    if origin is tuple:
        return _nested_tuple(value, where)
    raise ConfigError(f"[{where}] unsupported parameter type {hint!r}")  # pragma: no cover


def _nested_tuple(value: Any, where: str) -> Any:
    if isinstance(value, list | tuple):
        return tuple(_nested_tuple(v, where) for v in value)
    try:
        return float(value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{where}] must be an array of numbers, got {value!r}") from e


def check_probability(value: float, name: str) -> None:
    if not 0.0 <= value <= 1.0:
        raise ConfigError(f"'{name}' must be a probability in [0, 1], got {value}")


def check_nonnegative(value: float, name: str) -> None:
    if not value >= 0.0:
        raise ConfigError(f"'{name}' must be >= 0, got {value}")


def check_positive(value: float, name: str) -> None:
    if not value > 0.0:
        raise ConfigError(f"'{name}' must be > 0, got {value}")
