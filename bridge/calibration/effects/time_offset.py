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
    return latency_window(problem.t[fit][np.isfinite(problem.y[fit])])


def latency_window(t: Any) -> tuple[float, float]:
    """:func:`search_window` of the fit part's reading times ``t``."""
    if t.size < 10:
        return 0.0, 0.0
    step = float(np.median(np.diff(t))) / 2
    span = min(MAX_TIME_OFFSET_S, 0.05 * float(t[-1] - t[0]))
    return (step, span) if step > 0 and span >= step else (0.0, 0.0)


def correlations(t: Any, y: Any, reference: Any, taus: Any) -> Any:
    """The correlation of readings ``y`` at ``t`` with the reference shifted by each ``tau``."""
    t_ref, u_ref = reference
    yc = y - y.mean()
    out = np.full(len(taus), -np.inf)
    for i, tau in enumerate(taus):
        u = np.interp(t - tau, t_ref, u_ref)
        uc = u - u.mean()
        den = float(np.sqrt(np.dot(uc, uc) * np.dot(yc, yc)))
        if den > 0:
            out[i] = float(np.dot(uc, yc)) / den
    return out


def _fit_readings(problem: Any) -> tuple[Any, Any]:
    fit = problem.split.mask(problem.t, "fit")
    t, y = problem.t[fit], problem.y[fit]
    ok = np.isfinite(y)
    return t[ok], y[ok]


def coarse_lag(problem: Any, step: float, span: float, around: float = 0.0) -> float:
    """The ``tau`` of the grid ``(step, span)`` (:func:`search_window`), centred on ``around``
    (the clocks' offset, :func:`clock_offset`), whose shifted reference correlates best with
    the readings on the fit part; ``around`` without a grid, or when nothing correlates."""
    if not span:
        return around
    t, y = _fit_readings(problem)
    taus = around + np.arange(-span, span + step / 2, step)
    r = correlations(t, y, problem.reference, taus)
    return float(taus[int(np.argmax(r))]) if np.isfinite(r).any() else around


#: Clocks seconds apart (:func:`clock_offset`): searched over +-min(MAX_CLOCK_OFFSET_S,
#: CLOCK_SPAN_SHARE of the fit part) in at most 2 CLOCK_STEPS + 1 steps, on at most CLOCK_ROWS
#: readings; taken where the readings' variance the shifted reference leaves unexplained is
#: below CLOCK_VARIANCE_RATIO of the least within the latency window.
MAX_CLOCK_OFFSET_S = 10.0
CLOCK_SPAN_SHARE = 0.1
CLOCK_STEPS = 50
CLOCK_ROWS = 2000
CLOCK_VARIANCE_RATIO = 0.5


def clock_offset(problem: Any) -> tuple[float, float, float] | None:
    """``(tau, r, r_near)`` when a scalar stream and its reference are stamped on clocks
    seconds apart, else None: the shift ``tau`` beyond the latency window of
    :func:`search_window` at which the readings correlate best (``r``) with the reference, on
    the fit part, where the variance it leaves unexplained, ``1 - r^2``, is below
    :data:`CLOCK_VARIANCE_RATIO` of the least within the window (``r_near``, the largest
    correlation there by magnitude). A car's gyro with
    its clock 3 s off: 0.86 at +3.1 s against 0.57 within +-0.5 s (its error doubled, and
    nothing said it). Motion that repeats correlates about alike one period on, and is not
    taken; a reference mostly noise cannot explain enough to be."""
    scores = _clock_scores(problem)
    return None if scores is None else clock_pick(scores[2], scores[5], scores[4])


def _clock_scores(problem: Any) -> tuple[Any, Any, Any, Any, float, Any] | None:
    """``(t, y, taus, rows, span, r)``: the fit part's readings, the clock search's grid
    (:func:`clock_grid`) and the readings' correlation with the reference at each of its
    shifts; None without a reference or a grid."""
    if problem.reference is None:
        return None
    t, y = _fit_readings(problem)
    grid = clock_grid(t, problem.reference[0])
    if grid is None:
        return None
    taus, rows, span = grid
    return t, y, taus, rows, span, correlations(t[rows], y[rows], problem.reference, taus)


def clock_rival(problem: Any, tau: float) -> tuple[float, float, float] | None:
    """``(tau_2, r_2, r_1)`` when the scalar stream's readings match the reference about as well
    at another shift ``tau_2`` as at the clocks' offset ``tau`` (:func:`clock_offset`), each
    refined to half a sample on the fit part (``r_2``, ``r_1``): the unexplained variance at
    ``tau_2`` within ``1 / CLOCK_VARIANCE_RATIO`` of that at ``tau``. Motion that repeats
    matches itself a period on: a stepper sweeping an IMU back and forth every 7.8 s, its log
    3 s off, matched at +3.01 s (0.981) and at -4.79 s (0.984) on the fit part, and the coarse
    grid's 0.2 s steps, missing the sharp peaks, read 0.92 and 0.98. Else None."""
    scores = _clock_scores(problem)
    if scores is None:
        return None
    t, y, taus, rows, span, r = scores
    step, _ = latency_window(t)
    coarse = float(taus[1] - taus[0])
    # local maxima of the coarse grid beyond the latency window and away from tau
    inner = r[1:-1]
    peak = np.flatnonzero((inner >= r[:-2]) & (inner >= r[2:])) + 1
    peak = peak[(np.abs(taus[peak]) > span / 2) & (np.abs(taus[peak] - tau) > 2 * coarse)]
    if peak.size == 0:
        return None
    other = float(taus[peak[int(np.argmax(r[peak]))]])

    def refined(center: float) -> tuple[float, float]:
        fine = center + np.arange(-coarse, coarse + step / 2, step)
        rf = correlations(t[rows], y[rows], problem.reference, fine)
        k = int(np.argmax(rf))
        return float(fine[k]), float(rf[k])

    (_, r_1), (tau_2, r_2) = refined(tau), refined(other)
    if not 1 - r_2**2 < (1 - r_1**2) / CLOCK_VARIANCE_RATIO:
        return None
    return tau_2, r_2, r_1


def clock_reach(t: Any) -> float:
    """How far a clock offset is searched either way: min(:data:`MAX_CLOCK_OFFSET_S`,
    :data:`CLOCK_SPAN_SHARE` of the fit part, its reading times ``t``)."""
    return min(MAX_CLOCK_OFFSET_S, CLOCK_SPAN_SHARE * float(t[-1] - t[0]))


def clocks_note(tau: float, r: float, r_near: float, score: str, fitted: bool = True) -> str:
    """The note on readings whose stamps look ``tau`` s late against the reference's."""
    return (
        f"the readings match the reference best {tau:+.3g} s later ({score} {r:.2f}, "
        f"against {r_near:.2f} at most, by magnitude, near no shift): the readings' stamps "
        f"look about {tau:+.3g} s late against the reference's ("
        + ("a coarse search; time_offset, where it is tried, is fitted about it and says how "
           "far exactly" if fitted else "a coarse search; no time_offset is fitted on this "
           "stream")
        + "). Stamp both on one clock, or subtract that offset from the readings' t "
        "(docs/bundle-format.md: one clock for all files)"
    )


def clock_grid(t: Any, t_ref: Any) -> tuple[Any, Any, float] | None:
    """``(taus, rows, span)``: the shifts a clock offset is searched at (beyond the latency
    window ``span`` of :func:`latency_window`, out to +-min(:data:`MAX_CLOCK_OFFSET_S`,
    :data:`CLOCK_SPAN_SHARE` of the fit part)), and the fit part's readings (times ``t``) it is
    scored on: at most :data:`CLOCK_ROWS`, where the reference covers every shift. None where
    the fit part is too short to reach beyond the latency window."""
    step, span = latency_window(t)
    if not span:
        return None
    reach = clock_reach(t)
    coarse = max(step, reach / CLOCK_STEPS)
    k = int(reach / coarse)
    if k * coarse <= 2 * span:
        return None
    keep = np.flatnonzero((t >= t_ref[0] + k * coarse) & (t <= t_ref[-1] - k * coarse))
    rows = keep[:: max(1, keep.size // CLOCK_ROWS)]
    if rows.size < 10:
        return None
    return coarse * np.arange(-k, k + 1), rows, span


def clock_pick(taus: Any, r: Any, span: float) -> tuple[float, float, float] | None:
    """``(tau, r, r_near)`` from the scores ``r`` (a correlation, 1 a perfect match) of the
    shifts ``taus``: the best shift, when it lies beyond the inner half of the latency window
    ``span`` and the variance it leaves unexplained, ``1 - r^2``, is below
    :data:`CLOCK_VARIANCE_RATIO` of the least within that half (``r_near``, the largest score
    there by magnitude); else None. The inner half: an offset near the window's edge is found
    here too (the latency search is then centred on it), where a fit inside the window would
    stop at its edge and be rejected there (a compass 0.5 s off, at the edge of a 0.5 s
    window)."""
    near = np.abs(taus) <= span / 2
    best = int(np.argmax(r))
    if near[best] or not np.isfinite(r[best]) or not near.any():
        return None
    # by magnitude: readings of the opposite sign follow a motion that repeats half a period
    # later (a sign-flipped gyro on a rig turning back and forth read as a clock 3.5 s off)
    r_near = float(np.max(np.abs(r[near])))
    if not 1 - r[best] ** 2 < CLOCK_VARIANCE_RATIO * (1 - r_near**2):
        return None
    return float(taus[best]), float(r[best]), r_near


@register_effect("time_offset")
class TimeOffset(Effect):
    kinds = frozenset({"scalar", "odometry", "compass"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if problem.kind == "compass":
            return _propose_compass(self, problem)
        if problem.kind == "scalar" and (
            problem.reference is None or not reference_dominates(problem, self.name)
        ):
            return []
        if problem.kind != "scalar":  # odometry: from the clocks' coarse offset, or 0
            return [EffectInstance(self.name, self, ("tau_s",), (problem.clock_offset,))]
        step, span = search_window(problem)
        clocks = problem.clocks_apart
        around = 0.0 if clocks is None else clocks[0]
        return [EffectInstance(self.name, self, ("tau_s",),
                               (coarse_lag(problem, step, span, around),),
                               data={"span_s": span, "inside_s": span - step,
                                     "around_s": around})]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        inside = inst.data.get("inside_s")
        around = inst.data.get("around_s", 0.0)
        return inside is None or bool(abs(float(params[0]) - around) <= inside)

    def implausible_reason(self, inst: EffectInstance, params: Any, problem: Any) -> str | None:
        return (
            f"time_offset fitted as {float(params[0]):+.4g} s and rejected: at or beyond the "
            f"edge of the +-{inst.data['span_s']:.3g} s a latency is searched in"
            + (f" (about {inst.data['around_s']:+.3g} s, the clocks' offset)"
               if inst.data.get("around_s") else "")
            + ". Either the "
            "stream and the reference are stamped on clocks further apart (stamp both on one "
            "clock, or shift one; docs/bundle-format.md), or the shift stands in for something "
            "else (readings of the opposite sign match the reference half a period later)"
        )

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.tau = float(params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return {"calibration.time_offset_s": float(f"{params[0]:.6g}")}


def _propose_compass(effect: Effect, problem: Any) -> list[EffectInstance]:
    """A compass against a reference heading: ``tau`` starts at the shift of the latency
    window (about the clocks' offset, :attr:`.CompassProblem.clocks_apart`) where the declared
    model's heading follows the reference best (:meth:`.CompassProblem.heading_match`). Where
    that best lies at the window's edge the window moves on by its own width, while the match
    improves, up to the clocks' reach (a compass 0.5 s off beside a 10 s gap of the reference,
    whose clocks did not stand out: fitted at the edge, 0.51 s, and rejected). Against a sparse
    reference (each of its samples held against the mean of the readings around it) a latency
    within its interval is not told from the averaging's own error (a clean compass against a 1
    s reference got 35 ms): only clocks seconds apart are searched there."""
    if problem.mode != "heading" or problem.ref_t is None:
        return []
    step, span = problem.latency_window()
    if not span:
        return []
    clocks = problem.clocks_apart
    if clocks is None and problem.reading_dt is not None:
        return []
    around = 0.0 if clocks is None else clocks[0]
    t_fit = problem.t[problem.split.mask(problem.t, "fit")]
    reach = clock_reach(t_fit)
    best, score = around, -np.inf
    n_fit = int(t_fit.size)
    rows = np.arange(0, n_fit, max(1, n_fit // (2 * CLOCK_ROWS)))  # a start: 4000 rows do
    while True:
        taus = around + np.arange(-span, span + step / 2, step)
        match = problem.heading_match(taus, rows)
        if np.all(match == 1.0):
            return []  # no shift changes the match: a robot that does not turn, or steadily
        i = int(np.argmax(match))
        if float(match[i]) <= score:
            break
        best, score = float(taus[i]), float(match[i])
        edge = i in (0, taus.size - 1)
        if not edge or abs(best) + span > max(reach, span):
            break
        around = best
    # Clocks seconds apart are found on at most CLOCK_ROWS readings in coarse steps, and a car's
    # slow turns make a broad peak (a real compass shifted 2 s read +3.93 s there; least
    # squares then walked to 2.83 s, "beyond the window" about 3.93 s, and was rejected):
    # about them the fit may go as far as they were searched.
    inside = span - step if clocks is None else max(span - step, reach)
    return [EffectInstance(effect.name, effect, ("tau_s",), (best,),
                           data={"span_s": span, "inside_s": inside, "around_s": around})]
