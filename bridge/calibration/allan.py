"""Noise identification by Allan variance: the overlapping Allan deviation of a rate series and
the three noise terms of a gyro read from it.

IEEE Std 952-1997 (Annex C, "Allan variance method of random drift analysis") and IEEE Std
1554-2005 model the Allan variance of a gyro's rate as a sum of independent terms, each a straight
line of its own slope on a log-log plot of the Allan deviation sigma(tau)::

    sigma^2(tau) = N^2 / tau  +  (2 ln 2 / pi) B^2  +  K^2 tau / 3            (Annex C, Table C.2)

* N, angle random walk (white rate noise; rad/s/sqrt(Hz) = rad/sqrt(s)): slope -1/2, the line
  N / sqrt(tau) read at tau = 1 s;
* B, bias instability (flicker rate noise; rad/s): the flat part, read at the minimum of the
  curve as sigma_min / 0.664 (0.664 = sqrt(2 ln 2 / pi));
* K, rate random walk (rad/s^2/sqrt(Hz) = rad/s/sqrt(s)): slope +1/2, the line K sqrt(tau / 3)
  read at tau = 3 s.

The lines are fitted together, by non-negative weighted least squares of the Allan variance on
``[1/tau, 1, tau]``: each point's variance is ``2 sigma^4 / (M - 1)``, ``M = floor(n / m)`` the
number of independent clusters of ``m`` samples (the confidence of Annex C.1, percentage error of
sigma ``1 / sqrt(2 (M - 1))``; the overlapping estimate is more precise, so this is conservative),
reweighted by the fitted curve. Cluster sizes are octaves (m = 1, 2, 4, ...) with at least
:data:`MIN_CLUSTERS` clusters. Neighbouring points still share data, so the fit's least-squares
covariance is too small (1.6-1.7x on white noise plus a random walk); a term's standard error is
instead its reading at the best single point (:func:`reading_error`), which matches the spread
over seeds. B is read from the curve's minimum, not from the fitted flat term: that is the
standard reading, an upper bound on the flicker floor when the N and K lines meet near the
minimum.

Pure functions of arrays (no I/O); :func:`overlapping_adev` is NIST SP 1065 eq. 11 in the phase
form (W. J. Riley, "Handbook of Frequency Stability Analysis", 2008).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import optimize

FloatArray = NDArray[np.float64]

#: sqrt(2 ln 2 / pi): the Allan deviation of flicker rate noise of bias instability B is 0.664 B
FLICKER_FACTOR = float(np.sqrt(2 * np.log(2) / np.pi))
#: Smallest number of independent clusters a point of the curve needs (sigma within ~24 %)
MIN_CLUSTERS = 10
#: A point of the curve this many of its standard deviations from the fitted lines is off them
#: (the sd is the independent clusters' count's, larger than the overlapping estimate's: the
#: bar is conservative; more than one point must be off)
MISFIT_Z = 3.0
#: Where the lines are read (IEEE 952 Annex C): N at 1 s, K at 3 s
TAU_N_S = 1.0
TAU_K_S = 3.0


def octave_cluster_sizes(n: int, min_clusters: int = MIN_CLUSTERS) -> NDArray[np.int64]:
    """Cluster sizes 1, 2, 4, ... with at least ``min_clusters`` whole clusters in ``n``."""
    m_max = n // min_clusters
    if m_max < 1:
        return np.empty(0, dtype=np.int64)
    return np.asarray(2 ** np.arange(int(np.log2(m_max)) + 1), dtype=np.int64)


def overlapping_adev(
    rate: FloatArray, tau0: float, m: NDArray[np.int64]
) -> tuple[FloatArray, FloatArray]:
    """``(tau, sigma)``: overlapping Allan deviation of ``rate`` (samples every ``tau0`` s) at the
    cluster sizes ``m``; sigma in the unit of ``rate``.

    Phase form (NIST SP 1065 eq. 11): with the integrated series ``x_j = tau0 sum_{i<j} y_i``
    (``n + 1`` points), ``sigma^2(m tau0) = sum_j (x_{j+2m} - 2 x_{j+m} + x_j)^2 /
    (2 (m tau0)^2 (n + 1 - 2m))``.
    """
    y = np.asarray(rate, dtype=float)
    x = np.concatenate([[0.0], np.cumsum(y)]) * tau0
    tau = m * tau0
    sigma = np.empty(m.size)
    for k, mk in enumerate(m):
        d = x[2 * mk :] - 2 * x[mk:-mk] + x[: -2 * mk]
        sigma[k] = np.sqrt(np.mean(d**2) / (2 * tau[k] ** 2))
    return tau.astype(float), sigma


@dataclass(frozen=True)
class AllanFit:
    """The curve and the noise terms read from it (module docstring); units of a rate ``u``
    (rad/s for a gyro): ``N`` u/sqrt(Hz), ``B`` u, ``K`` u*sqrt(Hz) (u/s/sqrt(Hz))."""

    tau: FloatArray
    adev: FloatArray
    clusters: NDArray[np.int64]
    angle_random_walk: float
    angle_random_walk_se: float
    rate_random_walk: float
    rate_random_walk_se: float
    #: the curve's minimum / 0.664, and where it is
    bias_instability: float
    bias_instability_tau: float
    #: the fitted flat term (sqrt of its Allan variance / 0.664): 0 when no flicker floor shows
    bias_instability_fitted: float
    #: each point's distance from the fitted curve in its standard deviations (Annex C.1's
    #: ``sqrt(2 / (M - 1))`` of its Allan variance): beyond :data:`MISFIT_Z` at more than one
    #: point, the three lines do not describe the curve (:attr:`misfit`)
    misfit_z: FloatArray = field(default_factory=lambda: np.empty(0))

    @property
    def floor_reached(self) -> bool:
        """Whether the curve turns up after its minimum (the minimum is not the longest
        tau): otherwise B, read at the minimum, is only an upper bound on the flicker floor."""
        return bool(self.bias_instability_tau < self.tau[-1])

    @property
    def misfit(self) -> bool:
        """Whether more than one point lies beyond :data:`MISFIT_Z` of its standard deviations
        from the fitted curve: a shape the three terms do not make (a correlated process, a
        vibration's bump), so the fitted terms are no description of it (each still reads as
        its line at its tau)."""
        return bool(np.sum(np.abs(self.misfit_z) > MISFIT_Z) > 1)

    def model_adev(self, tau: FloatArray) -> FloatArray:
        """The fitted curve at ``tau``."""
        n, k = self.angle_random_walk, self.rate_random_walk
        b = FLICKER_FACTOR * self.bias_instability_fitted
        return np.asarray(np.sqrt(n**2 / tau + b**2 + k**2 * tau / 3), dtype=float)


def fit_noise_terms(
    tau: FloatArray, adev: FloatArray, clusters: NDArray[np.int64], iterations: int = 5
) -> AllanFit:
    """Fit ``N``, the flat term and ``K`` to an Allan deviation curve (module docstring)."""
    avar = adev**2
    A = np.column_stack([1 / tau, np.ones_like(tau), tau])
    dof = np.maximum(clusters - 1, 1).astype(float)
    # a point's sd is its model value times sqrt(2 / dof): floored relative to the curve, so a
    # point of (nearly) zero variance, or a term the fit drops, weighs much but finitely
    floor = max(float(np.max(avar)) * 1e-12, np.finfo(float).tiny)
    model = np.maximum(avar, floor)
    c = np.zeros(3)
    for _ in range(iterations):
        w = np.sqrt(dof / 2) / model  # 1 / sd of each point
        c, _ = optimize.nnls(A * w[:, None], avar * w)
        model = np.maximum(A @ c, floor)
    n, k = float(np.sqrt(c[0])), float(np.sqrt(3 * c[2]))
    delta = np.sqrt(2 / dof)  # relative sd of each point's Allan variance
    i = int(np.argmin(adev))
    return AllanFit(
        tau=tau,
        adev=adev,
        clusters=clusters,
        angle_random_walk=n,
        angle_random_walk_se=n * reading_error(delta, A[:, 0] * c[0] / model),
        rate_random_walk=k,
        rate_random_walk_se=k * reading_error(delta, A[:, 2] * c[2] / model),
        bias_instability=float(adev[i] / FLICKER_FACTOR),
        bias_instability_tau=float(tau[i]),
        bias_instability_fitted=float(np.sqrt(c[1]) / FLICKER_FACTOR),
        misfit_z=(avar - model) / (model * delta),
    )


def reading_error(delta: FloatArray, share: FloatArray) -> float:
    """Relative standard error of a term read off the curve at its best point: at a point whose
    Allan variance has relative sd ``delta`` and of which the term is the fraction ``share``, the
    term's Allan variance is read with relative sd ``delta / share``, its coefficient (a square
    root) with half that; the best point's. The fit combines all points, but neighbouring ones
    share data, and on white noise plus a random walk its spread is that of the best reading
    (within 10 %); nan for a term the fit does not hold."""
    with np.errstate(divide="ignore"):
        err = np.where(share > 0, delta / (2 * share), np.inf)
    best = float(np.min(err)) if err.size else float("inf")
    return best if np.isfinite(best) else float("nan")


def allan_noise(rate: FloatArray, tau0: float) -> AllanFit | None:
    """Overlapping Allan deviation of ``rate`` (every ``tau0`` s) at octave cluster sizes and the
    noise terms fitted to it; None when fewer than 3 cluster sizes fit (too short a series) or
    the series does not vary."""
    rate = np.asarray(rate, dtype=float)
    m = octave_cluster_sizes(rate.size)
    if m.size < 3 or not tau0 > 0:
        return None
    tau, adev = overlapping_adev(rate, tau0, m)
    if not np.all(np.isfinite(adev)) or not np.any(adev > 0):
        return None  # no noise to identify (a residual of exactly zero)
    return fit_noise_terms(tau, adev, rate.size // m)
