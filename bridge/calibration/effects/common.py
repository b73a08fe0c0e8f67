"""Helpers shared by the effect modules (config keys, categorical columns)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.robust import white_noise_sigma


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


#: The largest share of the reference's variance that may be its own noise when a gain is
#: fitted: the bias that noise gives the gain, relative, is about this share; 1 % is the
#: smallest held-out gain the selection counts (selection.MIN_RELATIVE_GAIN).
MAX_REFERENCE_NOISE_SHARE = 0.01


def reference_noise_share(problem: Any) -> float:
    """Share of the fit part's reference variance that is white noise (0 without a reference),
    the noise from first differences within each series of the stream (the rows of one value of
    its categorical columns: a sensor, a beacon), so interleaved series do not count as noise."""
    u = getattr(problem, "u", None)
    if u is None or not hasattr(problem, "t"):
        return 0.0
    fit = problem.split.mask(problem.t, "fit")
    uf = np.asarray(u, dtype=float)[fit]
    # the series of one sensor (landmark, tag, ...): the stream's categorical columns together
    columns = getattr(problem, "columns", {})
    names = [n for n in getattr(problem, "categorical_names", ()) if n in columns] or [
        n for n in ("sensor",) if n in columns]
    if names:
        cats = np.column_stack([np.asarray(columns[n], dtype=float)[fit] for n in names])
        ok = np.isfinite(uf) & np.all(np.isfinite(cats), axis=1)
        keys = np.unique(cats[ok], axis=0, return_inverse=True)[1].ravel().astype(float)
    else:
        ok = np.isfinite(uf)
        keys = np.zeros(int(ok.sum()))
    uf = uf[ok]
    if uf.size < 3:
        return 0.0
    # differences within each sensor's own series, so interleaved sensors are not noise
    order = np.argsort(keys, kind="stable")
    same = np.diff(keys[order]) == 0
    diffs = np.diff(uf[order])[same]
    var = float(np.var(uf))
    if var <= 0.0:
        return np.inf
    noise = white_noise_sigma(np.cumsum(np.r_[0.0, diffs])) if diffs.size else 0.0
    return noise**2 / var


def reference_dominates(problem: Any, effect: str) -> bool:
    """Whether a scalar stream's reference varies enough beyond its own noise to determine an
    effect fitted through it (a gain, a time offset: :func:`reference_noise_share` at most
    :data:`MAX_REFERENCE_NOISE_SHARE`); when not, a note on the stream says why the effect was
    not tried."""
    share = reference_noise_share(problem)
    if share <= MAX_REFERENCE_NOISE_SHARE:
        return True
    note = (
        f"{effect} not tried: the reference varies too little beyond its own noise (noise "
        f"{100 * min(share, 1.0):.3g} % of its variance on the fit part; fitted through it, a "
        "gain is pulled towards 0 by about that share and a time shift smooths the noise): "
        "record motion over a wider range, or a reference with less noise"
    )
    if note not in problem.notes:
        problem.notes.append(note)
    return False
