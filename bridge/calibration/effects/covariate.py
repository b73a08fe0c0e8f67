"""``covariate:<column>``: an error linear in an extra numeric column of the stream's CSV.

    y = ... + c * (z - mean_fit(z))      params: c (stream unit per column unit)

One instance per extra column that varies on the fit part (temperature, supply voltage, ...);
centring on the fit-part mean keeps ``c`` separate from a bias. Writes
``[sensors.<stream>.calibration] covariate_<column> = {coefficient, reference}``.

A covariate is an influence on the *error*, apart from the measured quantity. A column that
moves with the readings, in level and from instant to instant, is the measured quantity seen
through another channel (another axis of the same chip through its misalignment, a second sensor
of the same motion): where more than :data:`MAX_CHANNEL_R2` of its variance lies on a line
through the readings (:func:`line_r2`) *and* more than that share of its increments over
some interval up to ``MAX_LAG_S`` (0.5 s) on a line through the readings' increments
(:func:`fast_r2`), it is not proposed, and a note says so. Its coefficient would trade against
``scale``, and since the channel carries the sensor's own response to fast motion (its filter,
its timing), fitting it fits that response, not an error. Against the readings, not the
reference: the column shares the readings' clock, which the reference may not (with the gyro's
log stamped 0.3 s late the x rate followed the reference poorly and was fitted again). An
MPU-6050 on a rotary rig (ssong47/compute_relative_angle_between_two_IMUs): the x-axis rate (R^2
0.98 with the yaw readings, and of its 40 ms increments with theirs: a 1 % misalignment) came
with a coefficient of 35 and pulled the scale to -0.45, and the held-out heading error grew
sevenfold while the rate error fell.

Both, not the levels alone: a real influence can co-vary with the measured quantity through how
the recording went -- a chip that warms as a rate table steps its rate up (R^2 0.66 with the
readings), a supply that sags on long runs -- without moving with the readings within a second
(R^2 0.002 of the increments there); its coefficient is separable from a gain by that.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import (
    MAX_LAG_S,
    config_name,
    note_once,
    series_columns,
)

#: The share of a covariate's variance on a line through the readings, and of its increments on
#: a line through theirs, beyond which (both) the column is the measured quantity through another
#: channel: more of it follows the readings than varies on its own.
MAX_CHANNEL_R2 = 0.5


def line_r2(z: np.ndarray, other: np.ndarray) -> float:
    """R^2 of the line through ``other`` that best predicts ``z`` (the squared correlation; 0
    when either is constant or fewer than 3 rows are finite in both)."""
    ok = np.isfinite(z) & np.isfinite(other)
    z, other = z[ok], other[ok]
    if z.size < 3:
        return 0.0
    zc, pc = z - z.mean(), other - other.mean()
    den = float(np.dot(zc, zc) * np.dot(pc, pc))
    return float(np.dot(zc, pc) ** 2 / den) if den > 0 else 0.0


def fast_r2(
    z: np.ndarray, other: np.ndarray, t: np.ndarray, keys: np.ndarray | None = None
) -> float:
    """The largest :func:`line_r2` of ``m``-sample increments of ``z`` against those of
    ``other``, over ``m = 1, 2, 4, ...`` while ``m`` samples span at most ``MAX_LAG_S``; rows
    are taken in time order within each series (``keys``: one value per row, None: one series),
    increments never across two series."""
    n = z.size
    key = np.zeros(n) if keys is None else np.nan_to_num(np.asarray(keys, dtype=float), nan=-1e300)
    order = np.lexsort((t, key))
    z, other, t, key = z[order], other[order], t[order], key[order]
    same1 = key[1:] == key[:-1]
    dt = np.diff(t)[same1]
    step = float(np.median(dt)) if dt.size else 0.0
    best, m = 0.0, 1
    while m < n // 2 and (m == 1 or (step > 0 and m * step <= MAX_LAG_S)):
        same = key[m:] == key[:-m]
        best = max(best, line_r2((z[m:] - z[:-m])[same], (other[m:] - other[:-m])[same]))
        m *= 2
    return best


@register_effect("covariate")
class Covariate(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        out = []
        fit = problem.part("fit")
        cats = series_columns(problem, np.flatnonzero(problem.split.mask(problem.t, "fit")))
        keys = (None if cats is None else np.unique(
            np.nan_to_num(cats, nan=-1e300), axis=0, return_inverse=True)[1].ravel())
        # against the readings, not the reference: the column and the readings share a clock,
        # which the reference may not (a log stamped 0.3 s late hid the x rate)
        y = np.asarray(fit.y, dtype=float)
        for col in problem.covariate_names:
            z = np.asarray(fit.columns[col], dtype=float)
            finite = z[np.isfinite(z)]
            if finite.size < 3 or float(np.std(finite)) == 0.0:
                continue
            level = line_r2(z, y)
            fast = fast_r2(z, y, fit.t, keys) if level > MAX_CHANNEL_R2 else 0.0
            if fast > MAX_CHANNEL_R2:
                note_once(
                    problem,
                    f"covariate:{col} not tried: it follows the {problem.quantity} readings, "
                    f"in level (R^2 {level:.2g} on the fit part) and from instant to instant "
                    f"(R^2 {fast:.2g} of their increments within {MAX_LAG_S:g} s): it "
                    "is the measured quantity seen through another channel (another axis through "
                    "a misalignment, a second sensor of the same motion), and its coefficient "
                    "would be a second gain fitted to that channel's response, not an influence "
                    "on the error",
                )
                continue
            out.append(
                EffectInstance(
                    f"{self.name}:{col}",
                    self,
                    ("coefficient",),
                    (0.0,),
                    column=col,
                    data={"mean": float(np.mean(finite))},
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
