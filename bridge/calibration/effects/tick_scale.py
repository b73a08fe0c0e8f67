"""``tick_scale``: the distance per encoder tick differs from the declared one (both wheels).

    s_{l,r} = dticks_{l,r} / tpm      params: tpm (ticks per metre; speed/pose odometry: a factor
                                      on the travelled distance)

Writes ``[robot] ticks_per_metre`` (or ``[sensors.odometry.calibration] distance_scale``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance

#: a fitted tick size (or distance scale) beyond this factor of the declared one is implausible
MAX_TICK_FACTOR = 10.0
#: the reference's travel from its windows' starts must exceed this many of its own position
#: noise for a distance scale to be tried (OdometryProblem.reference_travel)
MIN_TRAVEL_JITTER = 10.0


@register_effect("tick_scale")
class TickScale(Effect):
    kinds = frozenset({"odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        travel, jitter = problem.reference_travel()
        if not travel > MIN_TRAVEL_JITTER * jitter:
            problem.notes.append(
                f"tick_scale not tried: the reference travels {travel:.3g} m RMS from its "
                f"windows' starts on the fit part, not beyond {MIN_TRAVEL_JITTER:g}x its own "
                f"position noise ({jitter:.3g} m): a distance scale does not show where the "
                "robot does not travel (turning on the spot); record it driving"
            )
            return []
        if problem.form == "ticks":
            return [EffectInstance(self.name, self, ("ticks_per_metre",), (problem.tpm,))]
        return [EffectInstance(self.name, self, ("distance_scale",), (1.0,))]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        """Within :data:`MAX_TICK_FACTOR` of the declared value either way (a distance scale may
        be negative: odometry that counts backwards in speed or pose form). A tick size that far
        off is a unit, or motion the position metric cannot see: a robot spinning on the spot
        with its tracker on the axle fitted 9.5e6 ticks/m against the declared 1e4, which makes
        the dead reckoning stand still (standard error 5e-14)."""
        value, declared = float(params[0]), float(inst.x0[0])
        if inst.param_names[0] != "ticks_per_metre":
            return bool(abs(value) <= MAX_TICK_FACTOR)
        return bool(declared / MAX_TICK_FACTOR <= value <= declared * MAX_TICK_FACTOR)

    def implausible_reason(self, inst: EffectInstance, params: Any, problem: Any) -> str | None:
        value = float(params[0])
        if not np.isfinite(value):
            return None
        return (
            f"tick_scale fitted as {value:.4g} (declared {float(inst.x0[0]):.4g}) and rejected: "
            f"beyond {MAX_TICK_FACTOR:g}x the declared either way, it is a unit (ticks per "
            "wheel turn for ticks per metre, mm for m) or motion the windows' positions cannot "
            "see (a robot turning on the spot, where no tick size moves it)"
        )

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        if inst.param_names[0] == "ticks_per_metre":
            state.tpm = float(params[0])
        else:
            state.distance_scale = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        if inst.param_names[0] == "ticks_per_metre":
            return {"/robot.ticks_per_metre": float(f"{params[0]:.6g}")}
        return {"calibration.distance_scale": float(f"{params[0]:.6g}")}

    def absent(self, inst: EffectInstance) -> Any:
        return np.asarray(inst.x0, dtype=float)  # proposed at the declared value
