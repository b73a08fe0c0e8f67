"""Helpers shared by the effect modules (config keys, categorical columns)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance


def config_name(name: str) -> str:
    """A TOML-friendly key for an effect name (``covariate:temperature_c`` -> ``covariate_...``)."""
    return name.replace(":", "_")


def scalar_config(
    inst: EffectInstance, params: Sequence[float], problem: Any, combine: str = "add"
) -> dict[str, Any]:
    """The native key with the total value, or ``calibration.<name>`` with named parameters."""
    native = problem.native_keys.get(inst.name)
    if native is not None and len(params) == 1:
        declared = problem.declared_values.get(inst.name, 0.0)
        if combine == "add":
            total = declared + float(params[0])
        else:  # multiplicative scale errors: (1 + declared)(1 + p) - 1
            total = (1 + declared) * (1 + float(params[0])) - 1
        return {native: _round(total)}
    return {
        f"calibration.{config_name(inst.name)}": {
            n: _round(float(v)) for n, v in zip(inst.param_names, params, strict=True)
        }
    }


def _round(v: float) -> float:
    return float(f"{v:.6g}")


def categorical_levels(values: np.ndarray, max_levels: int = 32) -> np.ndarray | None:
    """Sorted levels if ``values`` is integer valued with 2..max_levels distinct values."""
    v = values[np.isfinite(values)]
    if v.size == 0 or not np.all(v == np.round(v)):
        return None
    levels = np.unique(v)
    return levels if 2 <= levels.size <= max_levels else None


#: Smallest orientation spread (``CompassProblem.orientation_spread`` in calibration/streams/
#: compass.py) at which the iron effects are proposed: below it the data cannot tell them from the
#: constant. Here, not in the stream module, because effects sit below the streams that use them.
MIN_ORIENTATION_SPREAD = 0.1


def enough_orientations(problem: Any, harmonic: int, effect: str) -> bool:
    """Whether the compass stream's orientations can determine an iron effect
    (:meth:`calibration.streams.compass.CompassProblem.orientation_spread`); when not, a
    note on the stream says why the effect was not tried."""
    spread = float(problem.orientation_spread(harmonic))
    if spread >= MIN_ORIENTATION_SPREAD:
        return True
    note = (
        f"{effect} not tried: the orientations vary too little to tell it from the constant "
        f"(spread {spread:.3g} < {MIN_ORIENTATION_SPREAD:g}; turn the sensor through more angles)"
    )
    if note not in problem.notes:
        problem.notes.append(note)
    return False
