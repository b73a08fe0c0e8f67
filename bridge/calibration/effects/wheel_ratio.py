"""``wheel_ratio``: the left and right wheels have different diameters (UMBmark's E_d).

    s_l = dL / tpm * 2 rho / (1 + rho),  s_r = dR / tpm * 2 / (1 + rho)    params: rho = D_l / D_r

The mean distance per tick is kept, so ``rho`` is separate from ``tick_scale``. Tick odometry
only; starts from the declared ratio. Writes ``[robot] wheel_diameter_ratio`` (left / right), which
the simulator's drive and encoders read (sim/robot.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("wheel_ratio")
class WheelRatio(Effect):
    kinds = frozenset({"odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.form != "ticks":
            return []
        return [EffectInstance(self.name, self, ("ratio_left_right",), (problem.ratio,))]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        """A diameter ratio above 0 (at -1 one wheel counts backwards: a sign in the data,
        :func:`koala_bridge.calibration.streams.odometry.backward_wheel`)."""
        return bool(float(params[0]) > 0)

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.ratio = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"/robot.wheel_diameter_ratio": float(f"{params[0]:.6g}")}

    def absent(self, inst: EffectInstance) -> Any:
        return np.asarray(inst.x0, dtype=float)  # proposed at the declared ratio
