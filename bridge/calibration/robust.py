"""Robust statistics for the residual loop: a robust noise scale, a heavy-tail test, and the
two-component likelihood of a stream with spurious readings.

A stream whose readings are partly spurious (a sonar's floor and beam echoes, seeds/004 "Sensor
Models", 1. Beam-width Error and "noise (invalid data)") is a mixture::

    f(y_i) = (1 - p) N(r_i; 0, sigma^2) + p g(y_i | y_hat_i)

``r_i = y_i - y_hat_i`` the residual under the model, ``p`` the spurious fraction and ``g`` the
density of a spurious reading (``calibration.effects.outlier``). The functions here are pure: they
take residuals and log-densities and return numbers; the loop that fits ``p``, ``sigma`` and the
model jointly (EM) is :func:`koala_bridge.calibration.selection.fit_model`.
"""

from __future__ import annotations

import numpy as np
from koala_bridge.core.distributions import binom_sf, norm_sf
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: 1 / Phi^-1(3/4): the MAD of a Gaussian times this is its standard deviation (Huber, Robust
#: Statistics (1981), sec. 5.1).
MAD_TO_SIGMA = 1.4826
#: A residual beyond this many robust standard deviations is in the tail (Gaussian share 6.3e-5).
TAIL_Z = 4.0
#: False-alarm probability of the heavy-tail test on one stream.
TAIL_ALPHA = 0.01
#: False-alarm probability of the gross-error test: one reading so far out that no Gaussian
#: noise among the stream's readings reaches it (Bonferroni over the readings: about 6.1 robust
#: sigmas for 3000 of them)
GROSS_ALPHA = 1e-6
_LOG_SQRT_2PI = 0.5 * np.log(2 * np.pi)


def _deviations(r: FloatArray) -> FloatArray:
    """``|r - median r|`` of the finite residuals (empty where there are none)."""
    r = np.asarray(r, dtype=float)
    r = r[np.isfinite(r)]
    return np.abs(r - np.median(r)) if r.size else r


def mad_sigma(r: FloatArray) -> float:
    """1.4826 * median |r - median r|: the standard deviation of the Gaussian core of ``r``,
    unmoved by up to half the readings being spurious (Hampel 1974)."""
    dev = _deviations(r)
    return MAD_TO_SIGMA * float(np.median(dev)) if dev.size else 0.0


def white_noise_sigma(v: FloatArray) -> float:
    """The sigma of white noise on a series from its first differences (MAD, so the steps of
    the signal itself do not count): ``diff`` of white noise has variance ``2 sigma^2``."""
    v = np.asarray(v, dtype=float)
    return mad_sigma(np.diff(v[np.isfinite(v)])) / float(np.sqrt(2))


def _robust_z(r: FloatArray) -> FloatArray | None:
    """``|r - median r|`` over :func:`mad_sigma` for the finite residuals (the deviations
    computed once), or None where there are none or their MAD is 0."""
    dev = _deviations(r)
    s = MAD_TO_SIGMA * float(np.median(dev)) if dev.size else 0.0
    return dev / s if s > 0 else None


def tail_count(r: FloatArray, z: float = TAIL_Z) -> tuple[int, int]:
    """``(k, n)``: how many of the ``n`` finite residuals lie beyond ``z`` robust standard
    deviations of their median."""
    n = int(np.isfinite(np.asarray(r, dtype=float)).sum())
    scaled = _robust_z(r)
    return (0, n) if scaled is None else (int(np.sum(scaled > z)), n)


def heavy_tailed(
    r: FloatArray, declared_fraction: float = 0.0, z: float = TAIL_Z, alpha: float = TAIL_ALPHA
) -> bool:
    """Whether ``r`` holds more readings beyond ``z`` robust sigmas than Gaussian noise plus a
    declared share of spurious readings explains: the binomial tail
    ``P(K >= k | n, 2 Phi(-z) + declared_fraction) < alpha``. Every declared spurious reading is
    counted as if it fell in the tail, so the test is conservative against the declared model.

    Or one gross error: a reading beyond the reach of every reading the declared model
    expects, ``n (2 Phi(-z_max) + declared_fraction)`` < :data:`GROSS_ALPHA` (the declared
    spurious readings counted as in the tail again: a model that declares them expects one this
    far). The count alone misses it (one reading beyond 4 sigmas among 3000 is a Gaussian's
    19 %): a UWB range of -11.1 m against a true 3.1 m, 230 sigmas out, moved a plain
    least-squares fit of its anchor's offset by 2.2 standard errors, unsaid."""
    scaled = _robust_z(r)
    if scaled is None:
        return False
    k, n = int(np.sum(scaled > z)), scaled.size
    if n < 20 or k == 0:
        return False
    spurious = max(declared_fraction, 0.0)
    if binom_sf(k - 1, n, min(2 * norm_sf(z) + spurious, 1.0)) < alpha:
        return True
    return bool(n * (2 * norm_sf(float(np.max(scaled))) + spurious) < GROSS_ALPHA)


def gaussian_logpdf(r: FloatArray, sigma: float, shape: FloatArray | None = None) -> FloatArray:
    """``log N(r; 0, (sigma shape)^2)`` per reading; ``shape`` the declared relative noise level
    per reading (a sonar's distance-error table), None: 1."""
    s = max(float(sigma), 1e-300)
    r = np.asarray(r, dtype=float)
    if shape is None:
        return np.asarray(-0.5 * (r / s) ** 2 - np.log(s) - _LOG_SQRT_2PI, dtype=float)
    return np.asarray(
        -0.5 * (r / (s * shape)) ** 2 - np.log(s * shape) - _LOG_SQRT_2PI, dtype=float
    )


def _components(
    r: FloatArray, sigma: float, p: float, log_g: FloatArray, shape: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    p = float(np.clip(p, 0.0, 1.0))
    with np.errstate(divide="ignore"):
        a = np.log1p(-p) + gaussian_logpdf(r, sigma, shape)
        b = np.log(p) + np.asarray(log_g, dtype=float)
    return a, b


def mixture_loglik(
    r: FloatArray, sigma: float, p: float, log_g: FloatArray, shape: FloatArray | None = None
) -> float:
    """Sum over readings of ``log[(1 - p) N(r; 0, (sigma shape)^2) + p g]``, ``log_g`` = log g per
    reading (``-inf`` where a reading cannot be spurious). ``p = 0`` is the Gaussian likelihood."""
    a, b = _components(r, sigma, p, log_g, shape)
    return float(np.sum(np.logaddexp(a, b)))


def inlier_responsibility(
    r: FloatArray, sigma: float, p: float, log_g: FloatArray, shape: FloatArray | None = None
) -> FloatArray:
    """Posterior probability that each reading follows the model (the E step of EM,
    Dempster, Laird & Rubin 1977): ``(1 - p) N / ((1 - p) N + p g)``."""
    a, b = _components(r, sigma, p, log_g, shape)
    return np.asarray(np.exp(a - np.logaddexp(a, b)), dtype=float)


def weighted_rms(r: FloatArray, w: FloatArray) -> float:
    """``sqrt(sum w r^2 / sum w)``: the RMS of the readings a classification holds as inliers."""
    sw = float(np.sum(w))
    return float(np.sqrt(np.sum(w * np.asarray(r) ** 2) / sw)) if sw > 0 else float("nan")
