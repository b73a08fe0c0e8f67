"""``covariate:<column>``: an error linear in an extra numeric column of the stream's CSV.

    y = ... + c * (z - mean_fit(z))      params: c (stream unit per column unit)

One instance per extra column that varies on the fit part (temperature, supply voltage, ...);
centring on the fit-part mean keeps ``c`` separate from a bias. Writes
``[sensors.<stream>.calibration] covariate_<column> = {coefficient, reference}``.

A covariate is an influence on the *error*, apart from the measured quantity. A column that
mostly follows the reference is that quantity seen through another channel (another axis of the
same chip through its misalignment, a second sensor of the same motion): more than
:data:`MAX_REFERENCE_R2` of its variance on a line through the declared prediction, and it is not
proposed (a note says so). Its coefficient would trade against ``scale``, and since the channel
carries the sensor's own response to fast motion (its filter, its timing), fitting it fits that
response, not an error. An MPU-6050 on a rotary rig (ssong47/compute_relative_angle_between_two_
IMUs): the x-axis rate, R^2 0.83 with the reference yaw rate through a 1 % misalignment, came
with a coefficient of 35 and pulled the scale to -0.45, and the held-out heading error grew
sevenfold while the rate error fell.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import config_name, note_once

#: The largest share of a covariate's fit-part variance that may follow the declared prediction
#: (R^2 of a line through it): beyond half, the column is more the measured quantity than
#: anything of its own, and its coefficient is more a second gain than an influence on the error.
MAX_REFERENCE_R2 = 0.5


def reference_r2(z: np.ndarray, pred: np.ndarray) -> float:
    """R^2 of the line through ``pred`` that best predicts ``z`` (the squared correlation; 0
    when either is constant or fewer than 3 rows are finite in both)."""
    ok = np.isfinite(z) & np.isfinite(pred)
    z, pred = z[ok], pred[ok]
    if z.size < 3:
        return 0.0
    zc, pc = z - z.mean(), pred - pred.mean()
    den = float(np.dot(zc, zc) * np.dot(pc, pc))
    return float(np.dot(zc, pc) ** 2 / den) if den > 0 else 0.0


@register_effect("covariate")
class Covariate(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        out = []
        fit = problem.part("fit")
        pred = np.asarray(problem.curve(fit.u), dtype=float)
        for col in problem.covariate_names:
            z = fit.columns[col]
            r2 = reference_r2(np.asarray(z, dtype=float), pred)
            z = z[np.isfinite(z)]
            if z.size < 3 or float(np.std(z)) == 0.0:
                continue
            if r2 > MAX_REFERENCE_R2:
                note_once(
                    problem,
                    f"covariate:{col} not tried: {100 * r2:.3g} % of its variance follows the "
                    f"reference {problem.quantity} (R^2 on the fit part): it is the measured "
                    "quantity seen through another channel (another axis through a misalignment, "
                    "a second sensor of the same motion), and its coefficient would be a second "
                    "gain fitted to that channel's response, not an influence on the error",
                )
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
