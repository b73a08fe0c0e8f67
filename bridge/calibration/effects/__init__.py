"""Candidate effects: the library the residual loop draws from.

Each effect is one module of this package and one class registered with
``@register_effect("name")``. An effect knows which kinds of stream it applies to, proposes
instances of itself for a stream (``covariate:<column>`` proposes one per extra numeric column),
changes the stream's forward model through its ``apply`` hook, and says which config key it
writes. Adding an effect is adding one module and naming it in :data:`BUILTIN_MODULES`.

The registry follows IR-sim's ``@register_kinematics``: a name maps to one class, duplicates are
rejected, and the built-in modules are imported lazily on first use.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.errors import EffectRegistryError

__all__ = ["Effect", "EffectInstance", "available_effects", "get_effect", "register_effect"]

#: Modules holding the built-in effects, imported on first use of the registry.
BUILTIN_MODULES: tuple[str, ...] = (
    "bias",
    "scale",
    "bias_drift",
    "covariate",
    "offset_per",
    "range_dependent",
    "hard_iron",
    "soft_iron",
    "tick_scale",
    "wheel_base",
    "wheel_ratio",
    "heading_drift",
    "time_offset",
    "glitch",
    "quantisation",
    "outlier",
)

_REGISTRY: dict[str, type[Effect]] = {}


def register_effect(name: str) -> Callable[[type[Effect]], type[Effect]]:
    """Class decorator: register an :class:`Effect` subclass under ``name`` (unique)."""

    def decorate(cls: type[Effect]) -> type[Effect]:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise EffectRegistryError(f"effect {name!r} is already registered by {_REGISTRY[name]}")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return decorate


def _load_builtins() -> None:
    for module in BUILTIN_MODULES:
        importlib.import_module(f"{__name__}.{module}")


def available_effects() -> dict[str, Effect]:
    """Every registered effect, instantiated, by name (built-ins loaded on first call)."""
    _load_builtins()
    return {name: cls() for name, cls in sorted(_REGISTRY.items())}


def get_effect(name: str) -> Effect:
    """The registered effect ``name`` (the part before ``:`` for parametrised names)."""
    _load_builtins()
    base = name.split(":", 1)[0]
    if base not in _REGISTRY:
        raise EffectRegistryError(
            f"no effect named {base!r}; known: {', '.join(sorted(_REGISTRY))}"
        )
    return _REGISTRY[base]()
