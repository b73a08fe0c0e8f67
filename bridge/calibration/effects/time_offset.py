"""``time_offset``: latency between a stream and the reference.

    y(t) = model(u(t - tau))         params: tau (s; positive: the stream lags the reference)

For odometry the dead-reckoned pose stamped ``t + tau`` is compared with the reference at ``t``.
Needs a reference that is a time series (gyro, odometry). Writes
``[sensors.<stream>.calibration] time_offset_s``.

Least squares on ``tau`` alone finds the nearest local minimum: a reference with fast structure
(the drive's step jitter in a gyro's reference rate) has one about every half sample. So a
scalar stream's ``tau`` starts at the best of a grid, ``tau`` in steps of half the median sample
interval over +-min(0.5 s, 5 % of the fit part), scored by the correlation of the readings with
the shifted reference on the fit part (the cross-correlation peak, as in Kalibr's or
imu_utils' temporal alignment).

On a scalar stream a fitted ``tau`` that is not inside the window searched, by a grid step at
least, is implausible: at its edge the best latency may lie beyond it (the stream and the
reference stamped on clocks 0.8 s apart gave 0.499 s, and a gain of 0.07 came with it), and
beyond it least squares walked from the grid's best to a shift by a large part of the motion's
period, which stands in for something else (readings of the opposite sign matched half a period
later). Odometry's ``tau`` starts at 0, or where its clock is seconds off the reference's at
the coarse offset of :meth:`.OdometryProblem.coarse_clock_offset` (searched over
+-min(10 s, 10 % of the fit part)), and has no bound beyond that: an odometry log stamped on
another clock is a latency of any size.

A scalar stream's ``tau`` is determined by the reference's signal, not its noise: with a
reference that is mostly noise (a still gyro against a differentiated optical heading) a
fractional shift interpolates, that is smooths, the noise and looks like a gain. So it is
proposed only where the reference dominates its noise (:func:`.common.reference_dominates`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import reference_dominates

#: The largest latency searched on a scalar stream (s); the window searched, at most this, is
#: where a fitted one is plausible.
MAX_TIME_OFFSET_S = 0.5


def search_window(problem: Any) -> tuple[float, float]:
    """``(step, span)`` of the grid a scalar stream's ``tau`` is searched on: half the median
    sample interval, over +-min(:data:`MAX_TIME_OFFSET_S`, 5 % of the fit part); (0, 0) when
    the fit part is too short for one."""
    fit = problem.split.mask(problem.t, "fit")
    t = problem.t[fit][np.isfinite(problem.y[fit])]
    if t.size < 10:
        return 0.0, 0.0
    step = float(np.median(np.diff(t))) / 2
    span = min(MAX_TIME_OFFSET_S, 0.05 * float(t[-1] - t[0]))
    return (step, span) if step > 0 and span >= step else (0.0, 0.0)


def coarse_lag(problem: Any, step: float, span: float) -> float:
    """The ``tau`` of the grid ``(step, span)`` (:func:`search_window`) whose shifted reference
    correlates best with the readings on the fit part; 0 without a grid, or when nothing
    correlates."""
    if not span:
        return 0.0
    t_ref, u_ref = problem.reference
    fit = problem.split.mask(problem.t, "fit")
    t, y = problem.t[fit], problem.y[fit]
    ok = np.isfinite(y)
    t, y = t[ok], y[ok]
    taus = np.arange(-span, span + step / 2, step)
    yc = y - y.mean()
    best, best_r = 0.0, -np.inf
    for tau in taus:
        u = np.interp(t - tau, t_ref, u_ref)
        uc = u - u.mean()
        den = float(np.sqrt(np.dot(uc, uc) * np.dot(yc, yc)))
        r = float(np.dot(uc, yc)) / den if den > 0 else -np.inf
        if r > best_r:
            best, best_r = float(tau), r
    return best


@register_effect("time_offset")
class TimeOffset(Effect):
    kinds = frozenset({"scalar", "odometry"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.kind == "scalar" and (
            problem.reference is None or not reference_dominates(problem, self.name)
        ):
            return []
        if problem.kind != "scalar":  # odometry: from the clocks' coarse offset, or 0
            return [EffectInstance(self.name, self, ("tau_s",), (problem.clock_offset,))]
        step, span = search_window(problem)
        return [EffectInstance(self.name, self, ("tau_s",), (coarse_lag(problem, step, span),),
                               data={"span_s": span, "inside_s": span - step})]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        inside = inst.data.get("inside_s")
        return inside is None or bool(abs(float(params[0])) <= inside)

    def implausible_reason(self, inst: EffectInstance, params: Any, problem: Any) -> str | None:
        return (
            f"time_offset fitted as {float(params[0]):+.4g} s and rejected: at or beyond the "
            f"edge of the +-{inst.data['span_s']:.3g} s a latency is searched in. Either the "
            "stream and the reference are stamped on clocks further apart (stamp both on one "
            "clock, or shift one; docs/bundle-format.md), or the shift stands in for something "
            "else (readings of the opposite sign match the reference half a period later)"
        )

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.tau = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"calibration.time_offset_s": float(f"{params[0]:.6g}")}
