"""``heading_drift``: the dead-reckoned heading turns at a constant rate relative to the truth.

    dtheta_k = dtheta_model,k - d (t_k - t_(k-1))      params: d (rad/s)

A drift *in time* (rad/s), not per metre travelled: a heading error proportional to the signed
distance is ``wheel_ratio`` already (unequal wheel diameters add ``(1 - rho)/(1 + rho) ds / b``
to each turn), so the new reading is the one the geometry cannot give -- a fused or gyro-aided
heading whose rate is offset (a gyro bias in the robot's own odometry), or an encoder counting a
steady stream of spurious pulses on one side. It acts while the robot stands still, which is
what tells it from ``wheel_ratio`` on a recording with stops or changes of speed. ``d > 0``:
the odometry's heading turns counter-clockwise relative to the truth.

Every odometry form (ticks, speeds, pose). Writes ``[sensors.odometry.calibration]
heading_drift_rad_s`` (the simulator has no such key: it models neither a gyro-aided odometry
nor a spurious count rate).
"""

from __future__ import annotations

from typing import Any

from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("heading_drift")
class HeadingDrift(Effect):
    kinds = frozenset({"odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        return [EffectInstance(self.name, self, ("rate_rad_s",), (0.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.heading_drift = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"calibration.heading_drift_rad_s": float(f"{params[0]:.6g}")}
