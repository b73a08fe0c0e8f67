"""``covariate:<column>``: an error linear in an extra numeric column of the stream's CSV.

    y = ... + c * (z - mean_fit(z))      params: c (stream unit per column unit)

One instance per extra column that varies on the fit part (temperature, supply voltage, ...);
centring on the fit-part mean keeps ``c`` separate from a bias. Writes
``[sensors.<stream>.calibration] covariate_<column> = {coefficient, reference}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import config_name


@register_effect("covariate")
class Covariate(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        out = []
        fit = problem.part("fit")
        for col in problem.covariate_names:
            z = fit.columns[col]
            z = z[np.isfinite(z)]
            if z.size < 3 or float(np.std(z)) == 0.0:
                continue
            out.append(
                EffectInstance(
                    f"{self.name}:{col}",
                    self,
                    ("coefficient",),
                    (0.0,),
                    column=col,
                    data={"mean": float(np.mean(z))},
                )
            )
        return out

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        assert inst.column is not None
        z = np.nan_to_num(state.part.columns[inst.column] - inst.data["mean"])
        state.add = state.add + params[0] * z

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {
            f"calibration.{config_name(inst.name)}": {
                "coefficient": float(f"{params[0]:.6g}"),
                "reference": float(f"{inst.data['mean']:.6g}"),
            }
        }
