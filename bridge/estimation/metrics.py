"""How well a pose estimate tracks the truth: alignment, RMSE, NEES, kidnap recovery.

Pure functions of arrays (numpy, scipy.stats), no I/O. The bench
(bench/bench_localisation_hostile.py), the hostile-drive scenario
(:mod:`koala_bridge.tools.drive_scenario`) and the tests compute the issue-15 figures with them.

Conventions: poses are ``(x, y, theta)`` in m, m, rad, world frame; times are simulation seconds.
The estimation error of sample ``k`` is *estimate minus truth*,

    e_k = [x̂_k - x_k,  ŷ_k - y_k,  wrap(θ̂_k - θ_k)]            (wrap to (-pi, pi])

**Alignment** (:func:`align`). ``truth/pose`` is published at 50 Hz, ``estimate/pose`` at 20 Hz,
both stamped in simulation seconds. Every estimate sample inside the truth's time span is kept
and the truth is *linearly interpolated* at its time: x and y directly, theta after
``numpy.unwrap`` (so that an interpolation between 179° and -179° passes through 180°, not 0°),
then wrapped again. At 50 Hz a robot at 0.57 m/s moves 11 mm between truth samples and the
interpolation error of an arc is far below that. A teleport (a kidnap) is a discontinuity that
must not be interpolated across: estimate samples whose bracketing truth samples straddle one of
the given ``breaks`` are dropped (one sample per kidnap at most). Samples that fall exactly on a
truth time (every 0.1 s here) get the truth sample itself.

**RMSE** (:func:`pose_rmse`, :func:`heading_rmse_deg`): ``sqrt(mean(dx² + dy²))`` in m over the
position, ``sqrt(mean(wrap(dθ)²))`` converted to degrees over the heading.

**NEES** (:func:`nees`, :func:`nees_summary`; Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, §5.4.2): with ``P_k`` the published 3 x 3
covariance of ``(x, y, theta)``,

    eps_k = e_k^T P_k^-1 e_k

is chi-square with ``n = 3`` degrees of freedom when the estimator is consistent (zero-mean
Gaussian error with covariance ``P_k``). The two-sided 95 % band is
``[chi2.ppf(0.025, 3), chi2.ppf(0.975, 3)] = [0.216, 9.348]``; a consistent estimator has 95 %
of its samples inside, the issue-15 target asks >= 90 %. A covariance that is not positive
definite (or not finite) gives ``eps_k = inf``: such a sample is outside the band.
The average NEES ``mean(eps)`` of ``N`` *independent* samples satisfies
``N * mean(eps) ~ chi2(N n)``, so its two-sided 95 % interval is
``[chi2.ppf(0.025, N n) / N, chi2.ppf(0.975, N n) / N]``. Successive filter errors are
correlated in time, so for a run of N samples this interval is too narrow: it is a
strict test, read it as such (the fraction in band is the robust figure).

**Kidnap recovery** (:func:`kidnap_recovery`): with ``d_k = |(dx_k, dy_k)|`` the position error,
the recovery time is the first sample time ``t_r > t_kidnap`` from which ``d <= threshold`` holds
for every sample in ``[t_r, t_r + hold]`` (and the record reaches ``t_r + hold``); the recovery
duration is ``t_r - t_kidnap``. "Never" (None) when no such time exists in the record.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from koala_bridge.core.distributions import chi2_ppf
from koala_bridge.core.geometry import wrap_angle
from koala_bridge.estimation.errors import EstimationError
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

POSE_DOF = 3            # (x, y, theta)
BAND_PROBABILITY = 0.95  # two-sided chi-square band


@dataclass(frozen=True)
class AlignedPoses:
    """Estimate and truth at the same times.

    Attributes:
        t: ``(N,)`` simulation seconds (the estimate's times).
        truth: ``(N, 3)`` truth ``(x, y, theta)`` at ``t`` (interpolated, theta wrapped).
        estimate: ``(N, 3)`` estimated ``(x, y, theta)``.
        cov: ``(N, 3, 3)`` the estimate's covariance, or None when not given.
    """

    t: FloatArray
    truth: FloatArray
    estimate: FloatArray
    cov: FloatArray | None = None

    @property
    def error(self) -> FloatArray:
        """``(N, 3)`` estimate minus truth, heading wrapped to (-pi, pi]."""
        e = self.estimate - self.truth
        e[:, 2] = wrap_angle(e[:, 2])
        return e

    @property
    def position_error(self) -> FloatArray:
        """``(N,)`` Euclidean position error, m."""
        e = self.error
        return np.hypot(e[:, 0], e[:, 1])

    def window(self, start: float = -math.inf, end: float = math.inf) -> AlignedPoses:
        """The samples with ``start <= t < end``."""
        keep = (self.t >= start) & (self.t < end)
        return AlignedPoses(self.t[keep], self.truth[keep], self.estimate[keep],
                            None if self.cov is None else self.cov[keep])


def _series(t: ArrayLike, poses: ArrayLike, what: str) -> tuple[FloatArray, FloatArray]:
    tt = np.asarray(t, dtype=float).reshape(-1)
    pp = np.asarray(poses, dtype=float)
    if pp.ndim != 2 or pp.shape[1] != 3 or pp.shape[0] != tt.shape[0]:
        raise EstimationError(f"{what}: poses must be (N, 3) with N = len(t) = {tt.shape[0]}, "
                              f"got {pp.shape}")
    if tt.size and np.any(np.diff(tt) < 0):
        raise EstimationError(f"{what}: times must be non-decreasing")
    return tt, pp


def align(truth_t: ArrayLike, truth: ArrayLike, est_t: ArrayLike, estimate: ArrayLike,
          cov: ArrayLike | None = None, breaks: Sequence[float] = ()) -> AlignedPoses:
    """Put the truth at the estimate's times (linear interpolation, theta unwrapped first).

    Args:
        truth_t, truth: ``(T,)`` times and ``(T, 3)`` truth poses, times increasing.
        est_t, estimate: ``(N,)`` times and ``(N, 3)`` estimated poses.
        cov: optional ``(N, 3, 3)`` covariances of the estimate.
        breaks: times where the truth jumps (a kidnap: the robot is moved before the step at
            that time); an estimate sample with a truth sample at or before a break on one side
            and after it on the other is dropped (not interpolated across the jump).

    Estimate samples outside ``[truth_t[0], truth_t[-1]]`` are dropped.
    """
    tt, tp = _series(truth_t, truth, "truth")
    et, ep = _series(est_t, estimate, "estimate")
    cv = None
    if cov is not None:
        cv = np.asarray(cov, dtype=float)
        if cv.shape != (et.shape[0], 3, 3):
            raise EstimationError(f"cov must be (N, 3, 3) with N = {et.shape[0]}, got {cv.shape}")
    if tt.size < 2:
        raise EstimationError("truth: at least two samples are needed to align")
    keep = (et >= tt[0]) & (et <= tt[-1])
    # the truth samples bracketing each estimate time: tt[j - 1] < t <= tt[j]
    j = np.clip(np.searchsorted(tt, et, side="left"), 1, tt.size - 1)
    for b in breaks:
        straddles = (tt[j - 1] <= b) & (tt[j] > b) & (et > tt[j - 1]) & (et < tt[j])
        keep &= ~straddles
    et, ep = et[keep], ep[keep]
    if cv is not None:
        cv = cv[keep]
    theta = np.unwrap(tp[:, 2])
    truth_at = np.column_stack([
        np.interp(et, tt, tp[:, 0]),
        np.interp(et, tt, tp[:, 1]),
        wrap_angle(np.interp(et, tt, theta)),
    ])
    return AlignedPoses(et, truth_at, ep.copy(), cv)


def pose_rmse(aligned: AlignedPoses) -> float:
    """Position RMSE, m: ``sqrt(mean(dx² + dy²))`` (nan without samples)."""
    if aligned.t.size == 0:
        return math.nan
    e = aligned.error
    return float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))


def heading_rmse_deg(aligned: AlignedPoses) -> float:
    """Heading RMSE, degrees: ``sqrt(mean(wrap(dθ)²))`` (nan without samples)."""
    if aligned.t.size == 0:
        return math.nan
    return math.degrees(float(np.sqrt(np.mean(aligned.error[:, 2] ** 2))))


def nees(error: ArrayLike, cov: ArrayLike) -> FloatArray:
    """``(N,)`` normalised estimation error squared ``e_k^T P_k^-1 e_k``.

    ``error`` is ``(N, n)``, ``cov`` ``(N, n, n)``. A sample whose covariance is not finite or
    not positive definite gets ``inf`` (an estimator claiming zero or negative variance is
    inconsistent by definition).
    """
    e = np.asarray(error, dtype=float)
    p = np.asarray(cov, dtype=float)
    if e.ndim != 2 or p.shape != (e.shape[0], e.shape[1], e.shape[1]):
        raise EstimationError(f"nees: error (N, n) and cov (N, n, n) expected, got {e.shape} "
                              f"and {p.shape}")
    out = np.full(e.shape[0], np.inf)
    if e.shape[0] == 0:
        return out
    finite = np.all(np.isfinite(p), axis=(1, 2)) & np.all(np.isfinite(e), axis=1)
    sym = 0.5 * (p + np.swapaxes(p, 1, 2))
    ok = finite.copy()
    if np.any(finite):
        eig_min = np.full(e.shape[0], -1.0)
        eig_min[finite] = np.linalg.eigvalsh(sym[finite])[:, 0]
        ok &= eig_min > 0
    if np.any(ok):
        x = np.linalg.solve(sym[ok], e[ok][:, :, None])[:, :, 0]
        out[ok] = np.einsum("ij,ij->i", e[ok], x)
    return out


def chi2_band(dof: int = POSE_DOF, probability: float = BAND_PROBABILITY) -> tuple[float, float]:
    """The two-sided ``probability`` interval of a chi-square with ``dof`` degrees of freedom."""
    a = (1.0 - probability) / 2.0
    return chi2_ppf(a, dof), chi2_ppf(1.0 - a, dof)


@dataclass(frozen=True)
class NeesSummary:
    """NEES over a run: the fraction of samples in the chi-square band and the average NEES.

    Attributes:
        n: number of samples.
        band: the per-sample 95 % band ``(lo, hi)`` for ``dof``.
        fraction_in_band: share of samples with ``lo <= eps <= hi`` (nan without samples).
        fraction_above / fraction_below: shares above ``hi`` (over-confident) / below ``lo``.
        mean: average NEES.
        mean_interval: 95 % interval of the average NEES for ``n`` independent samples.
    """

    n: int
    dof: int
    band: tuple[float, float]
    fraction_in_band: float
    fraction_above: float
    fraction_below: float
    mean: float
    mean_interval: tuple[float, float]


def nees_summary(values: ArrayLike, dof: int = POSE_DOF,
                 probability: float = BAND_PROBABILITY) -> NeesSummary:
    """Summarise per-sample NEES ``values`` (module docstring for the formulas)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    lo, hi = chi2_band(dof, probability)
    n = int(v.size)
    if n == 0:
        return NeesSummary(0, dof, (lo, hi), math.nan, math.nan, math.nan, math.nan,
                           (math.nan, math.nan))
    a = (1.0 - probability) / 2.0
    interval = (chi2_ppf(a, n * dof) / n, chi2_ppf(1.0 - a, n * dof) / n)
    return NeesSummary(
        n, dof, (lo, hi),
        float(np.mean((v >= lo) & (v <= hi))),
        float(np.mean(v > hi)),
        float(np.mean(v < lo)),
        float(np.mean(v)),
        interval,
    )


@dataclass(frozen=True)
class KidnapRecovery:
    """When the estimate came back after a kidnap.

    Attributes:
        t_kidnap: when the robot was moved, s.
        t_recovered: first time from which the position error stayed <= ``threshold_m`` for
            ``hold_s``; None: never within the record.
        duration_s: ``t_recovered - t_kidnap`` or None.
        threshold_m, hold_s: the criterion.
    """

    t_kidnap: float
    t_recovered: float | None
    duration_s: float | None
    threshold_m: float
    hold_s: float


def kidnap_recovery(t: ArrayLike, position_error: ArrayLike, t_kidnap: float,
                    threshold_m: float = 0.2, hold_s: float = 1.0) -> KidnapRecovery:
    """First time after ``t_kidnap`` from which ``position_error <= threshold_m`` holds for
    ``hold_s`` seconds (every sample in ``[t_r, t_r + hold_s]``, and the record reaches
    ``t_r + hold_s``)."""
    if threshold_m <= 0 or hold_s < 0:
        raise EstimationError(f"kidnap_recovery: threshold_m must be > 0 and hold_s >= 0, got "
                              f"{threshold_m!r}, {hold_s!r}")
    tt = np.asarray(t, dtype=float).reshape(-1)
    d = np.asarray(position_error, dtype=float).reshape(-1)
    if tt.shape != d.shape:
        raise EstimationError(f"kidnap_recovery: t {tt.shape} and error {d.shape} differ")
    after = tt > t_kidnap
    tt, good = tt[after], d[after] <= threshold_m
    start: float | None = None
    for k in range(tt.size):
        if not good[k]:
            start = None
            continue
        if start is None:
            start = float(tt[k])
        if tt[k] - start >= hold_s - 1e-9:
            return KidnapRecovery(t_kidnap, start, start - t_kidnap, threshold_m, hold_s)
    return KidnapRecovery(t_kidnap, None, None, threshold_m, hold_s)


@dataclass(frozen=True)
class TrackingMetrics:
    """The issue-15 figures of one run (or one window of it)."""

    n: int
    pose_rmse_m: float
    heading_rmse_deg: float
    max_position_error_m: float
    nees: NeesSummary | None


def tracking_metrics(aligned: AlignedPoses) -> TrackingMetrics:
    """RMSE of position and heading, the largest position error and, with covariances, NEES."""
    n = int(aligned.t.size)
    summary = None
    if aligned.cov is not None:
        summary = nees_summary(nees(aligned.error, aligned.cov))
    return TrackingMetrics(
        n, pose_rmse(aligned), heading_rmse_deg(aligned),
        float(np.max(aligned.position_error)) if n else math.nan, summary,
    )
