"""``range_dependent``: an error that grows faster than linearly with the true range.

    y = ... + k * r^2        params: k (stream unit per m^2); r = true range (m)

An error proportional to range is ``scale``; this is the part growing with range beyond that
(beam spreading, a wrong speed-of-sound correction applied twice, ...). Range-type streams only,
and only where the true range varies on the fit part beyond its own noise
(:func:`.common.reference_dominates`): at one distance ``k r^2`` is an offset, and the held-out
part alone would pick it by extrapolation (a ToF sensor held at 25 cm once got ``k`` = -0.63).
Writes ``[sensors.<stream>.calibration] range_dependent = {k_per_m2}``.
"""

from __future__ import annotations

from typing import Any

from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import reference_dominates, scalar_config


@register_effect("range_dependent")
class RangeDependent(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if not problem.is_range or not reference_dominates(problem, self.name):
            return []
        return [EffectInstance(self.name, self, ("k_per_m2",), (0.0,))]

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.add = state.add + params[0] * state.part.u**2

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return scalar_config(inst, params, problem)
