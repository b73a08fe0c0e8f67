"""``offset_per:<column>``: one offset per level of a categorical column (sensor id, unit, ...).

    y = ... + o[level(z)],   sum over fit levels of o = 0     params: o_1 .. o_{L-1} (o_L = -sum)

Proposed for integer-valued columns with 2 to 32 levels on the fit part (the ``sensor`` column of
``range.csv`` among them). Levels not seen on the fit part get no offset. The sum-to-zero
constraint leaves the common level to the declared curve and ``bias``. Writes
``[sensors.ir] per_sensor_offset_counts`` for IR sensors (indexed by sensor id, added to the
declared offsets), otherwise
``[sensors.<stream>.calibration] offset_per_<column> = {levels, offsets}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import categorical_levels, config_name


def offsets_of(params: Any) -> np.ndarray:
    p = np.asarray(params, dtype=float)
    return np.r_[p, -p.sum()]


@register_effect("offset_per")
class OffsetPer(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        out = []
        fit = problem.part("fit")
        for col in problem.categorical_names:
            levels = categorical_levels(fit.columns[col])
            if levels is None:
                continue
            names = tuple(f"offset_{int(v)}" for v in levels[:-1])
            out.append(
                EffectInstance(
                    f"{self.name}:{col}",
                    self,
                    names,
                    (0.0,) * len(names),
                    column=col,
                    data={"levels": levels},
                )
            )
        return out

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        assert inst.column is not None
        levels = inst.data["levels"]
        z = state.part.columns[inst.column]
        i = np.clip(np.searchsorted(levels, z), 0, levels.size - 1)
        known = levels[i] == z
        state.add = state.add + np.where(known, offsets_of(params)[i], 0.0)

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        levels = inst.data["levels"]
        off = offsets_of(params)
        native = problem.native_keys.get(inst.name)
        if native is not None and levels.min() >= 0:
            # An increment per sensor id (config_update adds the declared offsets).
            full = np.zeros(int(levels.max()) + 1)
            full[levels.astype(int)] = off
            return {native: [float(f"{v:.6g}") for v in full]}
        return {
            f"calibration.{config_name(inst.name)}": {
                "levels": [float(v) for v in levels],
                "offsets": [float(f"{v:.6g}") for v in off],
            }
        }
