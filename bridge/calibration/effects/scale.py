"""``scale``: a gain error of a scalar measurement.

    y = (1 + s) * gain * curve(u) + ...          params: s (dimensionless)

Writes the native scale key (gyro: ``[sensors.gyro] scale_factor_error`` = (1 + declared)(1 + s)
- 1) or
``[sensors.<stream>.calibration] scale``.
"""

from __future__ import annotations

from typing import Any

from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import scalar_config


@register_effect("scale")
class Scale(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        return [EffectInstance(self.name, self, ("scale_error",), (0.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.gain = state.gain * (1.0 + params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return scalar_config(inst, params, problem, combine="mul")
