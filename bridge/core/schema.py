"""Small helpers for typed configuration: unknown keys are errors that suggest the nearest key.

Pure: no file I/O here. Loaders in ``bridge/`` read TOML and hand plain dicts to the
``from_dict`` constructors of ``sim/``, which call these helpers.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from typing import Any

from koala_bridge.core.errors import ConfigError  # re-exported: its old home


def reject_unknown(d: Mapping[str, Any], allowed: Iterable[str], section: str) -> None:
    """Raise :class:`ConfigError` for any key of ``d`` not in ``allowed``, suggesting the
    nearest."""
    allowed = list(allowed)
    for key in d:
        if key not in allowed:
            near = difflib.get_close_matches(key, allowed, n=1)
            hint = f"; did you mean '{near[0]}'?" if near else f"; valid keys: {', '.join(allowed)}"
            raise ConfigError(f"[{section}] unknown key '{key}'{hint}")


def require(d: Mapping[str, Any], key: str, section: str) -> Any:
    """Return ``d[key]`` or raise :class:`ConfigError` naming the missing key."""
    if key not in d:
        raise ConfigError(f"[{section}] missing required key '{key}'")
    return d[key]


def positive(value: Any, key: str, section: str) -> float:
    """Return ``value`` as a float, raising :class:`ConfigError` unless it is finite and > 0."""
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"[{section}] '{key}' must be a number, got {value!r}") from e
    if not v > 0 or v == float("inf"):
        raise ConfigError(f"[{section}] '{key}' must be > 0, got {value!r}")
    return v
