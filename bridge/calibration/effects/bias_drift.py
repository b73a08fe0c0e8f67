"""``bias_drift``: a bias that changes linearly in time.

    y = ... + d * (t - t_ref)      params: d (unit per second); t_ref = middle of the fit part

A random-walk bias cannot be predicted into held-out data beyond its last value, so the loop
tests the linear form; a random walk shows up as residual autocorrelation in the report.
Writes ``[sensors.<stream>.calibration] bias_drift = {rate_per_s, t_ref_s}``.
"""

from __future__ import annotations

from typing import Any

from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("bias_drift")
class BiasDrift(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        t_ref = 0.5 * (problem.split.t0 + problem.split.t1)
        return [EffectInstance(self.name, self, ("rate_per_s",), (0.0,), data={"t_ref": t_ref})]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.add = state.add + params[0] * (state.part.t - inst.data["t_ref"])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {
            "calibration.bias_drift": {
                "rate_per_s": float(f"{params[0]:.6g}"),
                "t_ref_s": float(f"{inst.data['t_ref']:.6g}"),
            }
        }
