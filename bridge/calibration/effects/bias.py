"""``bias``: a constant offset of a scalar measurement.

    y = gain * curve(u) + b          params: b (stream unit)

Writes the stream's native bias key (gyro: ``[sensors.gyro] bias_rad_s``, declared + b) or
``[sensors.<stream>.calibration] bias``. Not proposed where the declared model has a per-run
(turn-on) bias: that is a nuisance parameter, and a bias beyond its declared spread is added
by :func:`koala_bridge.calibration.pipeline.run_stream` instead.
"""

from __future__ import annotations

from typing import Any

from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import scalar_config


@register_effect("bias")
class Bias(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if getattr(problem, "turn_on_bias_sigma", 0.0) > 0:
            return []  # the declared per-run bias is a nuisance; see pipeline.run_stream
        return [EffectInstance(self.name, self, ("bias",), (0.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.add = state.add + params[0]

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        native = problem.native_keys.get(inst.name, "")
        if native.startswith("+"):  # a per-sensor key (IR offsets): the same increment for all
            n = int(problem.declared_values.get("n_sensors", 0))
            return {native: [float(f"{params[0]:.6g}")] * n}
        return scalar_config(inst, params, problem)
