"""``wheel_base``: the effective distance between the wheels' contact points differs.

    dtheta = (s_r - s_l) / b          params: b (m; speed/pose odometry: a factor on dtheta)

Writes ``[robot] wheel_base_m`` (or ``[sensors.odometry.calibration] yaw_scale``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("wheel_base")
class WheelBase(Effect):
    kinds = frozenset({"odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.form == "ticks":
            return [EffectInstance(self.name, self, ("wheel_base_m",), (problem.wheel_base,))]
        return [EffectInstance(self.name, self, ("yaw_scale",), (1.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        if inst.param_names[0] == "wheel_base_m":
            state.wheel_base = float(params[0])
        else:
            state.yaw_scale = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        if inst.param_names[0] == "wheel_base_m":
            return {"/robot.wheel_base_m": float(f"{params[0]:.6g}")}
        return {"calibration.yaw_scale": float(f"{params[0]:.6g}")}

    def absent(self, inst: EffectInstance) -> Any:
        return np.asarray(inst.x0, dtype=float)  # proposed at the declared value
