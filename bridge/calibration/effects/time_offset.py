"""``time_offset``: latency between a stream and the reference.

    y(t) = model(u(t - tau))         params: tau (s; positive: the stream lags the reference)

For odometry the dead-reckoned pose stamped ``t + tau`` is compared with the reference at ``t``.
Needs a reference that is a time series (gyro, odometry). Writes
``[sensors.<stream>.calibration] time_offset_s``.
"""

from __future__ import annotations

from typing import Any

from bridge.calibration.effects import register_effect
from bridge.calibration.effects.base import Effect, EffectInstance


@register_effect("time_offset")
class TimeOffset(Effect):
    kinds = frozenset({"scalar", "odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.kind == "scalar" and problem.reference is None:
            return []
        return [EffectInstance(self.name, self, ("tau_s",), (0.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.tau = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"calibration.time_offset_s": float(f"{params[0]:.6g}")}
