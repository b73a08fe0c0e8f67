"""``glitch``: readings stuck at one extreme value (max range, no echo) regardless of the range.

    y = g with probability p, else the model       params (fixed): p, g

Proposed when the largest (or smallest) reading of the fit part repeats (at least 3 times and
0.2 % of readings) and most of those readings lie far from what the declared model predicts
(more than 5 robust standard deviations). Readings equal to ``g`` are then scored as explained
by the glitch (residual 0); ``p`` is their fraction on the fit part. Range-type streams only.
Writes ``[sensors.<stream>] glitch_probability`` and ``calibration.glitch_value``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.robust import mad_sigma


@register_effect("glitch")
class Glitch(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if not problem.is_range:
            return []
        fit = problem.part("fit")
        y = fit.y
        if y.size < 20:
            return []
        r = problem.residuals([], problem.nuisance_x0(), "fit")
        mad = mad_sigma(r)
        best: tuple[int, float] | None = None
        for g in (float(np.max(y)), float(np.min(y))):
            hit = np.isclose(y, g, rtol=1e-9, atol=1e-12)
            n = int(hit.sum())
            if n < max(3, int(0.002 * y.size)) or n > 0.5 * y.size:
                continue
            if np.mean(np.abs(r[hit]) > 5 * max(mad, 1e-12)) < 0.5:
                continue
            if best is None or n > best[0]:
                best = (n, g)
        if best is None:
            return []
        n, g = best
        return [
            EffectInstance(self.name, self, ("probability", "value"), (n / y.size, g), fixed=True)
        ]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.glitch_value = float(params[1])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {
            "glitch_probability": float(f"{params[0]:.6g}"),
            "calibration.glitch_value": float(f"{params[1]:.6g}"),
        }
