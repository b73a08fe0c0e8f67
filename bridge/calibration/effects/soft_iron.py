"""``soft_iron``: axis gains and cross-coupling that turn the field's circle into an ellipse.

    m = S m_true + h,  corrected m_c = C (m - h),  C = (I + E) C_declared,  E symmetric, trace 0

params: ``e_xx, e_xy`` (planar, E = [[e_xx, e_xy], [e_xy, -e_xx]]) or ``e_xx, e_yy, e_xy, e_xz,
e_yz`` (sphere, e_zz = -e_xx - e_yy). The trace is fixed because the field magnitude is a nuisance
parameter: an overall gain is not observable. Writes ``[sensors.compass] soft_iron`` = S =
inverse of the total C (3x3).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import enough_orientations

#: Smallest (and, inverted, largest) axis gain of a plausible soft-iron correction.
MIN_GAIN = 0.5


def correction_matrix(params: Any) -> np.ndarray:
    """I + E as a 3x3 matrix from the 2 (planar) or 5 (sphere) parameters."""
    p = np.asarray(params, dtype=float)
    e = np.zeros((3, 3))
    if p.size == 2:
        e[0, 0], e[1, 1] = p[0], -p[0]
        e[0, 1] = e[1, 0] = p[1]
    else:
        e[0, 0], e[1, 1], e[2, 2] = p[0], p[1], -p[0] - p[1]
        e[0, 1] = e[1, 0] = p[2]
        e[0, 2] = e[2, 0] = p[3]
        e[1, 2] = e[2, 1] = p[4]
    return np.eye(3) + e


@register_effect("soft_iron")
class SoftIron(Effect):
    kinds = frozenset({"compass"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if not enough_orientations(problem, 2, "soft_iron"):
            return []
        names = ("e_xx", "e_xy") if problem.dims == 2 else ("e_xx", "e_yy", "e_xy", "e_xz", "e_yz")
        return [EffectInstance(self.name, self, names, (0.0,) * len(names))]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        """Axis gains within 2:1 of each other (eigenvalues of I + E in [0.5, 2]): magnetised
        parts near a sensor distort its field by tens of percent, not by collapsing an axis."""
        eig = np.linalg.eigvalsh(correction_matrix(params))
        return bool(np.all(eig >= MIN_GAIN) and np.all(eig <= 1 / MIN_GAIN))

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.C = correction_matrix(params) @ state.C

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        s = np.linalg.inv(correction_matrix(params) @ problem.C_declared)
        return {"soft_iron": [[float(f"{v:.6g}") for v in row] for row in s]}
