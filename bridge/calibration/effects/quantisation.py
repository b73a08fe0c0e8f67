"""``quantisation``: readings that take values on a lattice ``q * k`` only.

    y = q * round(model / q)         params (fixed): q (stream unit)

Proposed when at least 99 % of the fit part's readings lie within 1 % of a step of a multiple of
``q``, ``q`` the smallest gap between distinct readings (so unquantised data, whose gaps are
arbitrary, is never proposed). Least squares fits the other parameters on the unrounded model;
scoring rounds. Once it is in the model, further candidates are judged on the unrounded residual
(quantisation error as uniform noise of variance q^2/12, Widrow): the rounded residual is zero but
at rounding boundaries, and a few boundary flips would pass for strong evidence. Writes
``[sensors.<stream>.calibration] quantisation_step`` (not simulated).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


def lattice_step(y: np.ndarray, tolerance: float = 0.01, share: float = 0.99) -> float | None:
    """The lattice step of ``y`` or ``None`` when the values are not on one lattice."""
    y = y[np.isfinite(y)]
    u = np.unique(y)
    if u.size < 3:
        return None
    gaps = np.diff(u)
    scale = max(float(np.max(np.abs(u))), 1e-300)
    gaps = gaps[gaps > 1e-9 * scale]
    if gaps.size == 0:
        return None
    q = float(np.min(gaps))
    k = y / q
    if np.mean(np.abs(k - np.round(k)) < tolerance) < share:
        return None
    # Gaps must be (near) whole multiples of q too.
    g = gaps / q
    if np.mean(np.abs(g - np.round(g)) < tolerance) < share:
        return None
    return q


@register_effect("quantisation")
class Quantisation(Effect):
    kinds = frozenset({"scalar"})
    output_transform = True

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.angle:
            return []
        q = lattice_step(problem.part("fit").y)
        if q is None:
            return []
        return [EffectInstance(self.name, self, ("step",), (q,), fixed=True)]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.quant_step = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"calibration.quantisation_step": float(f"{params[0]:.6g}")}
