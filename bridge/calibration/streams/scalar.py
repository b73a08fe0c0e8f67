"""Scalar streams: one number per reading predicted from one reference quantity.

Gyro yaw rate (reference: rate of the reference heading), range sensors (reference: true range),
landmark range and bearing (reference: geometry of the reference pose and the landmark map).
Forward model, with the declared values and every effect's hook::

    y_hat = gain * curve(u(t - tau)) + add(t, covariates, u);  quantised: q round(y_hat / q)

``gain`` starts at 1 + declared scale error, ``add`` at the declared bias, ``curve`` is the
identity unless the stream measures raw counts (IR), where it is the declared response curve or,
declared only as a shape, a shared curve fitted on the fit part first (binned means, linear
interpolation). Readings the glitch effect explains (equal to its glitch value) score zero.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.effects.time_offset import clock_offset
from koala_bridge.calibration.problem import (
    FloatArray,
    Part,
    SecondaryMetric,
    StreamProblem,
    apply_all,
    effective_size,
    lag1_autocorrelation,
    split_params,
)
from koala_bridge.calibration.robust import (
    heavy_tailed,
    inlier_responsibility,
    mad_sigma,
    weighted_rms,
)
from koala_bridge.core.geometry import wrap_angle
from scipy.integrate import cumulative_trapezoid

log = logging.getLogger(__name__)


@dataclass
class ScalarPart:
    """The samples of one part of the split (or all), sliced once."""

    t: FloatArray
    y: FloatArray
    u: FloatArray
    columns: Mapping[str, FloatArray]


@dataclass
class ScalarState:
    """Mutable model state the effects change; see the module docstring for the equation."""

    part: ScalarPart
    u_at: Callable[[FloatArray, float], FloatArray] | None
    gain: float = 1.0
    add: FloatArray | float = 0.0
    tau: float = 0.0
    quant_step: float | None = None
    glitch_value: float | None = None

    def predict(self, curve: Callable[[FloatArray], FloatArray], rounding: bool) -> FloatArray:
        u = self.part.u
        if self.tau != 0.0 and self.u_at is not None:
            u = self.u_at(self.part.t, self.tau)
        y = self.gain * curve(u) + self.add
        if rounding and self.quant_step:
            y = self.quant_step * np.round(y / self.quant_step)
        return np.asarray(y, dtype=float)


def heading_metric(window_s: float) -> str:
    """The name of a rate stream's further metric: the RMS over the score part's ``window_s``
    windows of the heading error each accumulates to its end
    (:meth:`ScalarProblem.heading_window_error`)."""
    return f"heading_error_{window_s:g}s_window_rms"


def running_heading_metric(window_s: float) -> str:
    """The name of the metric a rate stream compared in heading space is scored by: the RMS
    over every sample of the heading error accumulated since its ``window_s`` window's start
    (the residual it is fitted by). Not :func:`heading_metric`'s window ends: over a window
    whose error grows evenly, the running RMS is ``1 / sqrt(3)`` of the end's (a new user's
    hand implementation of one read the other's figure, 0.0785 against 0.129 rad)."""
    return f"heading_error_{window_s:g}s_running_rms"


#: the effects a gyro's heading may show the practical size of
#: (:meth:`ScalarProblem.further_errors`): a rate offset, constant or linear in time, is a
#: heading drift by its physical reading. Any other would earn it through a correlation with a
#: slow error the held-out windows share: a bias that wanders (a random walk over a 10-minute
#: run) has the same sign in every window, so a slowly varying column (a warming chip's
#: temperature) that takes up a part of it lowers every window's heading error a little,
#: "significantly", and is no influence at all.
HEADING_EFFECTS = frozenset({"bias", "bias_drift"})


#: independent units per heading-space window for a residual that is a random walk
#: (:meth:`ScalarProblem.independent_count`): the least-squares slope of a random walk over a
#: window has 1.2 times the variance of its end over the window, and the mean square is half
#: the end's variance: (1 / 2) / (1.2 / 3) = 1.25
RANDOM_WALK_UNITS = 1.25


def _slope_variance_ratio(m: int, q: float, s2: float) -> float:
    """``F`` of :meth:`ScalarProblem.independent_count` for one window of ``m + 1`` samples
    ``r_j = W_j - (n_j - n_0)``, ``j = 0..m``: the variance of ``sum j r_j / sum j^2`` over
    ``mean_j var(r_j) / sum j^2``. ``var(sum j r_j) = q sum_ij i j min(i, j) + s2 (sum j^2 +
    (sum j)^2)``."""
    if m < 1:
        return 1.0
    j = np.arange(1, m + 1, dtype=float)
    b = float(np.sum(j**2))
    c = float(np.sum(j))
    # sum_i i min(i, j) for each j: the i <= j part sum i^2, the i > j part j sum i
    below = np.cumsum(j**2)
    above = c - np.cumsum(j)
    a = float(np.sum(j * (below + j * above)))
    mean_var = float(np.sum(q * j + 2.0 * s2)) / (m + 1)
    if mean_var <= 0.0:
        return 1.0
    return (q * a + s2 * (b + c**2)) / (b * mean_var)


@dataclass
class ScalarProblem(StreamProblem):
    """A scalar stream; see the module docstring. Built by :mod:`calibration.streams`."""

    t: FloatArray = field(default_factory=lambda: np.empty(0))
    y: FloatArray = field(default_factory=lambda: np.empty(0))
    u: FloatArray = field(default_factory=lambda: np.empty(0))
    columns: Mapping[str, FloatArray] = field(default_factory=dict)
    covariate_names: tuple[str, ...] = ()
    categorical_names: tuple[str, ...] = ()
    reference: tuple[FloatArray, FloatArray] | None = None  # (t_ref, u_ref) for time offsets
    angle: bool = False
    is_range: bool = False
    base_gain: float = 1.0
    base_add: FloatArray | float = 0.0
    curve_points: tuple[FloatArray, FloatArray] | None = None
    curve_fitted: bool = False
    heading_window_s: float | None = None
    quantity: str = "value"
    #: which series each row belongs to where rows of several interleave and no categorical
    #: column says so (the landmark of a camera observation): the reference's own noise is
    #: measured within each (effects.common.reference_noise_share)
    series: FloatArray | None = None
    #: the reference's noise share measured on the whole stream (effects.common), set by the
    #: pipeline on a decimated subset, whose random rows are not consecutive samples
    reference_share: float | None = None
    #: the whole stream, set by the pipeline on its decimated subset: the further metric
    #: (:meth:`further_errors`) is measured on it, since a random subset's rows integrate a white
    #: rate error into heading with ``k`` times its variance (``k`` the decimation factor)
    full: ScalarProblem | None = None
    #: compare in heading space: the residual rate integrated over windows of this length
    #: (re-anchored at each window start) instead of the rate residual itself; used when the
    #: reference heading is noisy (a compass), whose derivative is far noisier than its integral.
    integrate_window_s: float | None = None
    #: a gap between rows longer than this (s) starts a new window (of heading space, of the
    #: heading metric): the level segments of a gyro moved in 3-D, between which the tilted
    #: stretches are left out and the readings' trapezoid over the gap is no integral; None:
    #: windows run on over any gap
    window_gap_s: float | None = None
    #: the reference is a tracker's heading (``truth_pose.theta``), whose errors are far below
    #: a compass heading's: heading space may then use windows shorter than 10 s on a short
    #: recording (:func:`koala_bridge.calibration.streams._in_heading_space`)
    tracker_heading: bool = False
    #: the reference heading ``(t, rad)`` whose rate ``u`` is, and the interval the declared
    #: readings average over (``u`` is then the heading's change over it): a heading error
    #: (heading space, :meth:`heading_window_errors`) takes the reference's share as the
    #: heading's own change over each window, not as its differenced rate integrated over the
    #: readings' times. Errors of the heading (its noise, jitter of its stamps) then stay the
    #: size of one sample's, where through the rate they do not cancel.
    heading_ref: tuple[FloatArray, FloatArray] | None = None
    #: in heading space against a dense heading: that heading's noise share there
    #: (:meth:`heading_noise_share`), which a scale is judged against
    #: (``effects.common.reference_dominates``); None: the rate's share
    heading_share: float | None = None
    #: the reference's sample times when it is sparse beside the readings (a 13 Hz robot log
    #: against a 100 Hz gyro, ``streams.SPARSE_REFERENCE_RATIO``): the readings between two of its
    #: samples share its interpolation (:meth:`independent_count`)
    sparse_reference_t: FloatArray | None = None
    heading_interval_s: float | None = None
    #: sigma of a declared per-run (turn-on) bias: > 0 makes the bias a nuisance parameter of
    #: the declared model, fitted in every model (the ``bias`` effect is then judged against
    #: this spread instead, see :func:`koala_bridge.calibration.pipeline.run_stream`)
    turn_on_bias_sigma: float = 0.0
    #: the simulator's white-noise key of this stream (gyroscope_noise_density, count_noise_sigma)
    noise_key: str | None = None
    #: a known net rotation (t0, t1, rad) the bundle declares (meta.json reference): reported as
    #: the error of the rotation the model's corrected rate integrates to; not used to select
    known_rotation: tuple[float, float, float] | None = None
    #: the declared reporting range (min, max) of a range sensor: the support of its spurious
    #: readings (``calibration.effects.outlier``)
    range_limits: tuple[float, float] | None = None
    #: share of readings the declared model itself makes spurious (the simulator sonar's
    #: ``glitch_probability``): tails that this explains are not evidence of an outlier effect
    declared_outlier_probability: float = 0.0
    #: the declared noise sigma of each reading (a sonar's distance-error table at the true
    #: range), None: one sigma for all; used by the likelihood of spurious readings only
    noise_sigma: FloatArray | None = None

    def __post_init__(self) -> None:
        fit = self.split.mask(self.t, "fit")
        self._parts = {
            "fit": self._slice(fit),
            "score": self._slice(~fit),
            # every row in order: the arrays themselves (nothing writes into a part)
            "all": ScalarPart(self.t, self.y, self.u, dict(self.columns)),
        }
        base_add = np.broadcast_to(np.asarray(self.base_add, dtype=float), self.t.shape)
        self._base_add = {"fit": base_add[fit], "score": base_add[~fit], "all": base_add}
        self._robust_scale: tuple[float | None] | None = None
        self._excess: dict[str, FloatArray] = {}  # _reference_excess at tau = 0, per part
        self._heading_cum: FloatArray | None = None
        self._full_cum: FloatArray | None = None
        self._shape: dict[str, FloatArray] = {}
        if self.noise_sigma is not None:
            sig = np.asarray(self.noise_sigma, dtype=float)
            # a zero declared sigma (the table's first row) would make one reading decisive
            sig = np.maximum(sig, 0.1 * float(np.median(sig[fit])) if fit.any() else 1e-9)
            self._shape = {"fit": sig[fit], "score": sig[~fit], "all": sig}

    def _slice(self, m: np.ndarray) -> ScalarPart:
        return ScalarPart(
            self.t[m], self.y[m], self.u[m], {k: v[m] for k, v in self.columns.items()}
        )

    def part(self, part: str) -> ScalarPart:
        return self._parts[part]

    # ----- model -------------------------------------------------------------------------------
    def curve(self, u: FloatArray) -> FloatArray:
        if self.curve_points is None:
            return u
        return np.interp(u, self.curve_points[0], self.curve_points[1])

    def _u_at(self, t: FloatArray, tau: float) -> FloatArray:
        assert self.reference is not None
        return np.interp(t - tau, self.reference[0], self.reference[1])

    def nuisance_x0(self) -> FloatArray:
        return np.zeros(1) if self.turn_on_bias_sigma > 0 else np.empty(0)

    def state(self, part: str) -> ScalarState:
        return ScalarState(
            self._parts[part],
            self._u_at if self.reference is not None else None,
            gain=self.base_gain,
            add=self._base_add[part].copy(),
        )

    def _evaluated(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str, for_fit: bool
    ) -> tuple[ScalarState, FloatArray]:
        """The model state of ``part`` with every effect applied, and its residual."""
        st = self.state(part)
        if self.turn_on_bias_sigma > 0:
            st.add = st.add + x[0]
        apply_all(st, self, insts, x)
        y_hat = st.predict(self.curve, rounding=not for_fit)
        r = st.part.y - y_hat
        if self.angle:
            r = wrap_angle(r)
        if st.glitch_value is not None:
            r = np.where(np.isclose(st.part.y, st.glitch_value, rtol=1e-9, atol=1e-12), 0.0, r)
        return st, r

    def _residual(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str, for_fit: bool
    ) -> FloatArray:
        return self._evaluated(insts, x, part, for_fit)[1]

    def residuals(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: Part, for_fit: bool = False
    ) -> FloatArray:
        if self.integrate_window_s is not None:
            t = self._parts[part].t
            return self._integrate(t, self._increments(insts, x, part, for_fit),
                                   self.integrate_window_s, self.window_gap_s)
        return self._residual(insts, x, part, for_fit)

    def _increments(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str, for_fit: bool = False
    ) -> FloatArray:
        """The heading error the residual rate adds between consecutive samples of ``part``
        (rad, one fewer than the samples).

        The readings' side is the trapezoid of ``y - add``; the reference's is ``gain`` times the
        reference heading's change between the two samples' times (``- tau``), when the stream
        has that heading (:attr:`heading_ref`): summed over a window it is the heading's own
        change, whatever noise the heading or its stamps hold, where the trapezoid of its
        differenced rate would keep a 2 ms jitter of a stamp as a rate error of ``w 2 ms / dt``
        weighted by the readings' intervals, which does not cancel. On a decimated subset of a
        long stream (:attr:`full` set) the readings' side between two of its rows is their
        integral on the whole stream: the trapezoid over the subset's random gaps is no integral
        of the motion, which then would not cancel against the heading's change. Without the
        heading, the trapezoid of the residual rate.
        """
        st, r = self._evaluated(insts, x, part, for_fit)
        t = st.part.t
        dt = np.diff(t)
        inc = 0.5 * (r[1:] + r[:-1]) * dt
        if self.heading_ref is None or t.size < 2:
            return np.asarray(inc, dtype=float)
        assert self.curve_points is None, "a heading reference is a gyro's: no response curve"
        # y - gain u - add, with gain's share of it on the heading's change instead:
        # + gain (trapezoid of u - change of the heading)
        inc = inc + st.gain * self._reference_excess(part, st.tau)
        if self.full is not None:
            y = st.part.y
            inc = inc - 0.5 * (y[1:] + y[:-1]) * dt + np.diff(self._whole_integral(t))
        return np.asarray(inc, dtype=float)

    def _whole_integral(self, t: FloatArray) -> FloatArray:
        """The whole stream's readings (:attr:`full`) integrated (trapezoid) from its start to
        ``t``, linear between its samples (a subset's rows are among them)."""
        assert self.full is not None
        if self._full_cum is None:
            self._full_cum = cumulative_trapezoid(self.full.y, self.full.t, initial=0.0)
        return np.asarray(np.interp(t, self.full.t, self._full_cum), dtype=float)

    def _reference_excess(self, part: str, tau: float) -> FloatArray:
        """Per interval of ``part``: the trapezoid of the reference rate at ``t - tau`` minus
        the reference heading's change over it (what integrating the differenced rate adds to
        the heading's own change); cached for ``tau = 0``."""
        if tau == 0.0 and part in self._excess:
            return self._excess[part]
        p = self._parts[part]
        u = p.u if tau == 0.0 or self.reference is None else self._u_at(p.t, tau)
        out = 0.5 * (u[1:] + u[:-1]) * np.diff(p.t) - np.diff(self._heading_at(p.t - tau))
        if tau == 0.0:
            self._excess[part] = out
        return out

    def _heading_at(self, t: FloatArray) -> FloatArray:
        """The reference heading at ``t`` (linear between its samples); with a declared sample
        interval ``I``, its mean over the ``I`` before ``t``, whose rate the declared readings
        are (``(h(t) - h(t - I)) / I``, :func:`koala_bridge.calibration.streams.build_gyro`)."""
        assert self.heading_ref is not None
        tr, hr = self.heading_ref
        interval = self.heading_interval_s
        if not interval:
            return np.asarray(np.interp(t, tr, hr), dtype=float)
        if self._heading_cum is None:
            # the exact integral of the linear interpolant at its samples
            self._heading_cum = cumulative_trapezoid(hr, tr, initial=0.0)
        cum = self._heading_cum
        slope = np.diff(hr) / np.diff(tr)

        def integral(s: FloatArray) -> FloatArray:
            # from the sample at or before s, the trapezoid under the line to s; held at the
            # first (last) value before (after) the samples
            k = np.clip(np.searchsorted(tr, s, side="right") - 1, 0, tr.size - 2)
            ds = np.clip(s, tr[0], tr[-1]) - tr[k]
            inside = cum[k] + hr[k] * ds + 0.5 * slope[k] * ds**2
            before = np.minimum(s - tr[0], 0.0) * hr[0]
            after = np.maximum(s - tr[-1], 0.0) * hr[-1]
            return np.asarray(inside + before + after, dtype=float)

        return (integral(t) - integral(t - interval)) / interval

    @cached_property
    def clocks_apart(self) -> tuple[float, float, float] | None:
        """Whether the stream and its reference look stamped on clocks seconds apart
        (:func:`koala_bridge.calibration.effects.time_offset.clock_offset`), searched once: the
        pipeline's note and ``time_offset``'s start both ask."""
        return clock_offset(self)

    @staticmethod
    def _windows(
        t: FloatArray, window_s: float, gap_s: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per row of ``t``: its ``window_s`` window's number (from ``t[0]``, and from the first
        row after each gap longer than ``gap_s``: :attr:`window_gap_s`), and the row its window
        starts at (the latest start, not the running maximum of anything: a heading error that
        falls from one window to the next is re-anchored as well)."""
        if gap_s is None or t.size < 2:
            k = np.floor((t - t[0]) / window_s).astype(int)
            start = np.r_[True, k[1:] != k[:-1]]
        else:
            piece = np.r_[0, np.cumsum(np.diff(t) > gap_s)]
            first = np.r_[0, np.flatnonzero(np.diff(piece)) + 1]
            within = np.floor((t - t[first][piece]) / window_s).astype(int)
            start = np.r_[True, (piece[1:] != piece[:-1]) | (within[1:] != within[:-1])]
            k = np.cumsum(start) - 1
        return k, np.maximum.accumulate(np.where(start, np.arange(t.size), 0))

    @staticmethod
    def _integrate(
        t: FloatArray, inc: FloatArray, window_s: float, gap_s: float | None = None
    ) -> FloatArray:
        """The sum of the increments ``inc`` (one per interval of ``t``) from the start of each
        ``window_s`` window: each window starts from zero."""
        if t.size < 2:
            return np.zeros(t.shape)
        _, anchor = ScalarProblem._windows(t, window_s, gap_s)
        c = np.r_[0.0, np.cumsum(inc)]
        return np.asarray(c - c[anchor], dtype=float)

    def independent_count(self, part: Part, r: FloatArray | None = None) -> float | None:
        """In heading space, what the residual ``r`` of ``part`` is worth in independent units
        for a bias (a ramp from each window's start); None in rate space.

        Inside a window (each starts from the reference heading at its first sample) the
        residual is ``W_j - (n_j - n_0)``: ``W`` the integral of the readings' white noise, a
        random walk of variance ``q`` per sample, ``n`` the reference heading's white noise of
        variance ``s2``, shared by the whole window at its anchor. Their lag-1 autocorrelation
        from differences, which ``n`` dominates, counted every sample as independent (a still
        gyro's bias had a standard error of 5e-6 rad/s for an error of 2e-4). Here ``q`` and
        ``s2`` come from the residual's variogram inside the windows, the line
        ``V_h = h q + 2 s2`` through its values at an eighth and a quarter of a window (noise
        that a filter smooths, or the reference's interpolation, is white at that scale: the
        differences' lag-1 would have called it a random walk), and a window of ``m`` samples
        counts ``m / F``, ``F`` the variance of the least-squares slope over the ramp under that
        model over what independent residuals of the same mean square would give. A pure random
        walk gives 1.25 units per window (the slope's variance ``1.2 q / T`` against the window
        end's ``q / T``), a pure white heading noise 2.67 (its anchor is shared): it is at least
        1.25 per window whatever the mixture, and slow structure the model lacks counts as
        random walk, so fewer. Without ``r``: 1.25 per window.

        In rate space against a sparse reference (:attr:`sparse_reference_t`), see
        :meth:`_sparse_reference_count`; else None."""
        if self.integrate_window_s is None:
            return self._sparse_reference_count(part, r)
        t = self._parts[part].t
        if t.size < 2:
            return 0.0
        k, _ = self._windows(t, self.integrate_window_s, self.window_gap_s)
        sizes = np.bincount(k)
        sizes = sizes[sizes >= 2]
        if r is None or r.size != t.size:
            return RANDOM_WALK_UNITS * float(sizes.size)
        # the variogram's line at the window's scale, lags an eighth and a quarter of a window:
        # noise a filter smooths (an accelerometer's angle) levels off long before, and is
        # white there; a random walk keeps growing. At short lags both grow.
        h2 = max(2, int(np.median(sizes)) // 4)
        h1 = max(1, h2 // 2)

        def variogram(lag: int) -> float:
            same = k[lag:] == k[:-lag]
            d = (r[lag:] - r[:-lag])[same]
            return float(np.mean(d**2)) if d.size else 0.0

        v1, v2 = variogram(h1), variogram(h2)
        q = max((v2 - v1) / (h2 - h1), 0.0)
        s2 = max((v2 - h2 * q) / 2.0, 0.0)
        if q + s2 <= 0.0:
            return RANDOM_WALK_UNITS * float(sizes.size)
        return float(sum(size / _slope_variance_ratio(int(size) - 1, q, s2) for size in sizes))

    def heading_noise_share(self) -> float:
        """The reference heading's noise share in heading space, on the fit part: what a scale
        fitted there is pulled towards 0 by (errors in the variables), in [0, 1]; 0 without a
        heading or a window.

        The regressor is the heading's path from each window's start, ``P``; the readings'
        integral over the same windows, ``Q``, follows its motion times the gain and shares
        none of its noise. A per-window ramp (a bias) is projected out of both, the gain ``g``
        is that of ``Q`` on ``P`` the other way round (``Q.Q / P.Q``, clean of ``P``'s noise;
        held within 2:1 and signed, as in rate space), and the share is ``1 - P.Q / (g P.P)``:
        the part of the heading's path the readings do not follow. A sign-flipped gyro's share
        read 1 unsigned ("the readings do not follow it"), and its sign note was never reached.
        A heading's white noise alone (sixth differences) missed noise that a filter smooths (a
        low-passed accelerometer angle): its windows' changes looked like motion, and a still
        gyro got a scale of -1. The heading is read at the clocks' offset when the stream's
        clock is seconds off the reference's (:attr:`clocks_apart`)."""
        if self.heading_ref is None or self.integrate_window_s is None:
            return 0.0
        p = self._parts["fit"]
        t = p.t
        if t.size < 4:
            return 0.0
        _, anchor = self._windows(t, self.integrate_window_s, self.window_gap_s)
        # read where the readings' clock puts it (a gyro 3 s off read as 24 % noise)
        path = self._heading_at(t - (0.0 if self.clocks_apart is None else self.clocks_apart[0]))
        path = path - path[anchor]
        readings = self._integrate(t, 0.5 * (p.y[1:] + p.y[:-1]) * np.diff(t),
                                   self.integrate_window_s, self.window_gap_s)
        tau = t - t[anchor]
        tt = float(np.dot(tau, tau))
        if tt > 0:
            path = path - tau * float(np.dot(path, tau)) / tt
            readings = readings - tau * float(np.dot(readings, tau)) / tt
        pp, pq, qq = (float(np.dot(a, b)) for a, b in
                      ((path, path), (path, readings), (readings, readings)))
        if pp <= 0.0 or pq == 0.0:
            return 1.0
        # signed, as in rate space: readings that run against the heading (a sign convention)
        # follow its path as well as any, and a scale tried then names the sign
        gain = float(np.sign(pq) * np.clip(qq / abs(pq), 0.5, 2.0))
        return float(np.clip(1.0 - pq / (gain * pp), 0.0, 1.0))

    def _sparse_reference_count(self, part: Part, r: FloatArray | None) -> float | None:
        """Against a sparse reference, the larger of two AR(1) counts (``effective_size``):
        over the readings, and over the residual's means per reference interval. Readings
        between two reference samples share the reference's interpolation there: a 13 Hz robot
        log against a 100 Hz gyro left residuals whose lag-1 autocorrelation (0.999) counted 8 s
        of them as 3 units, and a scale of -0.115 had a standard error of 0.11 where a fit per
        reference interval gives 0.022. A gyro's own white noise, when it is what the residual
        holds, keeps the readings' count. None without a sparse reference or ``r``."""
        if self.sparse_reference_t is None or r is None:
            return None
        t = self._parts[part].t
        if r.size != t.size or r.size < 3:
            return None
        k = np.searchsorted(self.sparse_reference_t, t)
        rows = np.bincount(k)
        held = rows > 0
        means = np.bincount(k, weights=r)[held] / rows[held]
        return max(effective_size(int(r.size), lag1_autocorrelation(r)),
                   effective_size(int(means.size), lag1_autocorrelation(means)))

    def se_variance(self, part: Part, r: FloatArray, rss: float, n_params: int) -> float:
        """In heading space ``rss / (n_eff - p)``, ``n_eff`` the units of
        :meth:`independent_count`: with a few windows the parameters take a share of the
        degrees of freedom that ``n - p`` would not show (on a still gyro's 36 s fit part, the
        bias's standard error then lies within 10 % of its spread over 400 seeds, 25 % under
        it with ``n - p``)."""
        units = self.independent_count(part, r)
        if units is None:
            return super().se_variance(part, r, rss, n_params)
        return rss / max(max(units, 2.0) - n_params, 1.0)

    def residual_series(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        if self.integrate_window_s is not None:
            return self.t, self._integrate(
                self.t, self._increments(insts, x, "all"), self.integrate_window_s,
                self.window_gap_s,
            )
        return self.t, self._residual(insts, x, "all", False)

    # ----- metrics -----------------------------------------------------------------------------
    # ----- robust statistics -------------------------------------------------------------------
    def noise_shape(self, part: Part | str) -> FloatArray | None:
        return self._shape.get(part)

    def readings(self, part: Part | str) -> FloatArray:
        return self._parts[part].y

    def tail_residual(self) -> FloatArray:
        """The declared model's fit-part residual (over the declared noise sigma, when there is
        one) without the readings at a repeated extreme value (max range, no echo: the
        ``glitch`` effect's, which scores them apart)."""
        r = self.residuals([], self.nuisance_x0(), "fit")
        if "fit" in self._shape:
            r = r / self._shape["fit"]
        y = self._parts["fit"].y
        keep = np.isfinite(r)
        if y.size:
            for g in (float(np.max(y)), float(np.min(y))):
                hit = np.isclose(y, g, rtol=1e-9, atol=1e-12)
                if hit.sum() >= 3:
                    keep &= ~hit
        return r[keep]

    def robust_scale(self) -> float | None:
        if self._robust_scale is None:
            scale = None
            if self.integrate_window_s is None and self.t.size:
                if heavy_tailed(self.tail_residual(), self.declared_outlier_probability):
                    scale = mad_sigma(self.residuals([], self.nuisance_x0(), "fit")) or None
            self._robust_scale = (scale,)
        return self._robust_scale[0]

    def inlier_weights(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str
    ) -> FloatArray | None:
        """Posterior inlier probability of each reading of ``part`` under the model's mixture
        effect (``calibration.effects.outlier``); None without one."""
        mix = [
            (i, p)
            for i, p in zip(insts, split_params(self, insts, x), strict=True)
            if i.effect.mixture
        ]
        if not mix:
            return None
        inst, p = mix[-1]
        r = self._residual(insts, x, part, False)
        log_g = inst.effect.log_density(inst, p, self._parts[part].y, r)
        return inlier_responsibility(r, float(p[1]), float(p[0]), log_g, self._shape.get(part))

    def heading_window_errors(
        self, insts: Sequence[EffectInstance], x: FloatArray, window_s: float
    ) -> FloatArray:
        """The heading error the residual rate accumulates over each score-part window (rad).

        Each window of ``window_s`` seconds starts from zero error (re-anchored to the
        reference); its value is the sum of :meth:`_increments` over the window.
        Windows covered less than 90 % are left out, unless no window is full.
        """
        p = self._parts["score"]
        if p.t.size < 2:
            return np.empty(0)
        k, _ = self._windows(p.t, window_s, self.window_gap_s)
        dt = np.diff(p.t)
        inc = self._increments(insts, x, "score")
        same = k[1:] == k[:-1]
        sums = np.bincount(k[1:][same], weights=inc[same], minlength=int(k.max()) + 1)
        span = np.bincount(k[1:][same], weights=dt[same], minlength=int(k.max()) + 1)
        full = span >= 0.9 * window_s
        if not np.any(full):
            full = span > 0
        return sums[full]

    def heading_window_error(
        self, insts: Sequence[EffectInstance], x: FloatArray, window_s: float
    ) -> float:
        """RMS of :meth:`heading_window_errors` (rad)."""
        e = self.heading_window_errors(insts, x, window_s)
        return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")

    def rotation_error(self, insts: Sequence[EffectInstance], x: FloatArray) -> float:
        """Integral over the known rotation's interval of the rate the model infers from the
        readings, ``(y - add) / gain`` (trapezoid), minus the known rotation (rad)."""
        assert self.known_rotation is not None
        t0, t1, known = self.known_rotation
        st = self.state("all")
        if self.turn_on_bias_sigma > 0:
            st.add = st.add + x[0]
        apply_all(st, self, insts, x)
        rate = (self.y - np.broadcast_to(st.add, self.y.shape)) / st.gain
        m = (self.t >= t0) & (self.t <= t1)
        t, r = self.t[m], rate[m]
        return float(np.sum(0.5 * (r[1:] + r[:-1]) * np.diff(t)) - known) if t.size > 1 else np.nan

    def further_errors(
        self,
        old: tuple[Sequence[EffectInstance], FloatArray],
        new: tuple[Sequence[EffectInstance], FloatArray],
    ) -> tuple[str, FloatArray, FloatArray] | None:
        """A rate sensor's heading (:meth:`heading_window_errors`), what a gyro is read for, for
        a candidate (``new``'s last effect) of :data:`HEADING_EFFECTS`. A rate error small
        beside the fast motion's (filter lag, vibration) can be most of the heading error it
        integrates to, as a bias of 0.02 rad/s beside a 12.5 Hz oscillation is."""
        src = self.full or self
        if src.heading_window_s is None or new[0][-1].name not in HEADING_EFFECTS:
            return None
        w = src.heading_window_s
        return (
            heading_metric(w),
            src.heading_window_errors(*old, w),
            src.heading_window_errors(*new, w),
        )

    def secondary_metrics(
        self,
        before: tuple[Sequence[EffectInstance], FloatArray],
        after: tuple[Sequence[EffectInstance], FloatArray],
    ) -> list[SecondaryMetric]:
        out = []
        w = self.inlier_weights(*after, "score")
        if w is not None:
            # Both on the readings the final model holds as inliers (posterior weights), so
            # before and after are compared on the same readings; rms_error keeps all of them.
            out.append(
                SecondaryMetric(
                    "inlier_rms_error",
                    self.unit,
                    weighted_rms(self._residual(*before, "score", False), w),
                    weighted_rms(self._residual(*after, "score", False), w),
                )
            )
        if self.heading_window_s is not None:
            w = self.heading_window_s
            out.append(
                SecondaryMetric(
                    heading_metric(w),
                    "rad",
                    self.heading_window_error(*before, w),
                    self.heading_window_error(*after, w),
                )
            )
        if self.known_rotation is not None:
            out.append(
                SecondaryMetric(
                    "known_rotation_error",
                    "rad",
                    self.rotation_error(*before),
                    self.rotation_error(*after),
                    signed=True,
                )
            )
        return out

    def noise_estimate(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[str | None, float | None]:
        if self.noise_key is None or self.integrate_window_s is not None or self.t.size < 3:
            return None, None
        r = self._residual(insts, x, "all", False)
        w = self.inlier_weights(insts, x, "all")
        # with spurious readings in the model, the noise is the inliers'
        sigma = float(np.std(r)) if w is None else weighted_rms(r - np.average(r, weights=w), w)
        if self.noise_key == "gyroscope_noise_density":
            # Kalibr: sample sigma = density / sqrt(dt), dt the mean interval (the sensor's
            # rate): a logger's irregular stamps make the median far shorter than the rate.
            dt = (self.t[-1] - self.t[0]) / (self.t.size - 1)
            return self.noise_key, sigma * float(np.sqrt(dt))
        if self.noise_key == "count_noise_sigma":
            return self.noise_key, float(np.sqrt(max(sigma**2 - 1 / 12, 0.0)))
        return self.noise_key, sigma

    def config_values(self, insts: Sequence[EffectInstance], x: FloatArray) -> dict[str, Any]:
        if self.curve_fitted and self.curve_points is not None:
            # The simulator's IR response table ([sensors.ir], sim/sensors/ir.py IrConfig).
            return {
                "response_range_m": [round(float(v), 6) for v in self.curve_points[0]],
                "response_counts": [round(float(v), 3) for v in self.curve_points[1]],
            }
        return {}

    def describe(self) -> dict[str, Any]:
        return {
            "samples": int(self.t.size),
            "quantity": self.quantity,
            "curve": "fitted shared curve"
            if self.curve_fitted
            else ("declared curve" if self.curve_points is not None else "identity"),
        }


def fit_shared_curve(
    u: FloatArray, y: FloatArray, max_levels: int = 50, bins: int = 20
) -> tuple[FloatArray, FloatArray]:
    """A response curve declared only as a shape: binned means of y over u, sorted by u.

    Distinct reference values (up to ``max_levels``) are their own bins (a set-up with known
    distances); otherwise ``bins`` quantile bins. Linear interpolation between bin centres,
    clamped outside.
    """
    ok = np.isfinite(u) & np.isfinite(y)
    u, y = u[ok], y[ok]
    levels = np.unique(u)
    if levels.size <= max_levels:
        idx = np.searchsorted(levels, u)
        xs = levels
    else:
        edges = np.unique(np.quantile(u, np.linspace(0, 1, bins + 1)))
        idx = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, edges.size - 2)
        xs = np.bincount(idx, weights=u) / np.maximum(np.bincount(idx), 1)
    counts = np.bincount(idx, minlength=xs.size)
    ys = np.bincount(idx, weights=y, minlength=xs.size) / np.maximum(counts, 1)
    keep = counts > 0
    return np.asarray(xs[keep], dtype=float), np.asarray(ys[keep], dtype=float)
