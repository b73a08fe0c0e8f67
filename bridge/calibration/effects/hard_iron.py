"""``hard_iron``: a constant field offset added by magnetised parts on the robot.

    m = m_true + h       (corrected as m_c = C (m - h))      params: dh_x, dh_y[, dh_z] (data unit)

Two components for planar modes, three for a full-sphere recording. Starting value: with a heading
reference the linear least-squares solution of ``m_i = R(-theta_i) b + h`` (b the horizontal
field in the world frame); without, the algebraic circle/sphere fit ``|m|^2 = 2 h.m + c``
(both exact for noise-free data). Plausible only within ``3 max|m|`` of zero (``m = f + h``
bounds ``|h| <= 2 max|m|`` once the orientations vary). Writes ``[sensors.compass]
hard_iron_uT`` (declared + found, converted to uT).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import enough_orientations
from koala_bridge.core.geometry import circle_centre


@register_effect("hard_iron")
class HardIron(Effect):
    kinds = frozenset({"compass"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if not enough_orientations(problem, 1, "hard_iron"):
            return []
        d = problem.dims
        fit = problem.split.mask(problem.t, "fit")
        m = problem.m[fit]
        if problem.mode == "heading":
            th = problem.theta_ref[fit]
            c, s = np.cos(th), np.sin(th)
            # m_x = c b_x + s b_y + h_x ; m_y = -s b_x + c b_y + h_y
            n = len(th)
            a = np.zeros((2 * n, 4))
            a[:n, 0], a[:n, 1], a[:n, 2] = c, s, 1.0
            a[n:, 0], a[n:, 1], a[n:, 3] = -s, c, 1.0
            sol, *_ = np.linalg.lstsq(a, np.r_[m[:, 0], m[:, 1]], rcond=None)
            h = sol[2:4]
        else:
            h = circle_centre(m[:, :d])
        dh = h - problem.h_declared[:d]
        names = ("dh_x", "dh_y", "dh_z")[:d]
        # m = f + h with f the outside field: once the orientations vary (checked above), some
        # reading is at least as long as f, so |h| <= |m| + |f| <= 2 max|m|; beyond 3 max|m|
        # the fit is not a hard iron (a sphere through a circle runs off along its normal).
        bound = 3.0 * float(np.max(np.linalg.norm(problem.m[:, :d], axis=1)))
        return [EffectInstance(self.name, self, names, tuple(float(v) for v in dh),
                               data={"max_offset": bound,
                                     "declared": problem.h_declared[:d].copy()})]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        h = np.asarray(inst.data["declared"], dtype=float) + np.asarray(params, dtype=float)
        return bool(np.linalg.norm(h) <= inst.data["max_offset"])

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        h = state.h.copy()
        h[: len(params)] += params
        state.h = h

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        h = problem.h_declared.copy()
        h[: len(params)] += params
        return {"hard_iron_uT": [float(f"{v * problem.uT_per_unit:.6g}") for v in h]}
