"""``tick_scale``: the distance per encoder tick differs from the declared one (both wheels).

    s_{l,r} = dticks_{l,r} / tpm      params: tpm (ticks per metre; speed/pose odometry: a factor
                                      on the travelled distance)

Writes ``[robot] ticks_per_metre`` (or ``[sensors.odometry.calibration] distance_scale``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("tick_scale")
class TickScale(Effect):
    kinds = frozenset({"odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.form == "ticks":
            return [EffectInstance(self.name, self, ("ticks_per_metre",), (problem.tpm,))]
        return [EffectInstance(self.name, self, ("distance_scale",), (1.0,))]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        """Ticks per metre above 0 (a distance scale may be negative: odometry that counts
        backwards in speed or pose form)."""
        return inst.param_names[0] != "ticks_per_metre" or bool(float(params[0]) > 0)

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        if inst.param_names[0] == "ticks_per_metre":
            state.tpm = float(params[0])
        else:
            state.distance_scale = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        if inst.param_names[0] == "ticks_per_metre":
            return {"/robot.ticks_per_metre": float(f"{params[0]:.6g}")}
        return {"calibration.distance_scale": float(f"{params[0]:.6g}")}

    def absent(self, inst: EffectInstance) -> Any:
        return np.asarray(inst.x0, dtype=float)  # proposed at the declared value
