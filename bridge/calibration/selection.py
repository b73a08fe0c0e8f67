"""Greedy forward selection of effects, with an explicit statistical stopping rule.

Per stream, starting from the declared model (nuisance parameters fitted):

1. every candidate effect not yet in the model is added in turn and all parameters are refitted
   on the fit part (``scipy.optimize.least_squares``);
2. a candidate *passes* when all three hold:

   * **fit-part BIC improves**: ``n_f ln(RSS_new / RSS_old) + k ln(n_f) < 0`` (Schwarz 1978),
   * **held-out likelihood-ratio test**: ``L = n_s ln(RSS_s,old / RSS_s,new)`` exceeds the
     chi-square quantile ``chi2_k(1 - alpha / K)``; ``alpha = 0.01``, ``K`` the number of
     candidates tried in this round (Bonferroni), ``k`` the effect's parameter count;
   * **practical size**: held-out RMS drops by at least 1 %, or, when it drops by less (but
     does drop), a further held-out metric the stream names for the candidate
     (:meth:`StreamProblem.further_errors`: a gyro's heading for its bias or bias drift, where
     a bias too small to show beside the rate error of fast motion is most of the heading
     error) drops by at least 1 % *and* significantly: a one-sided paired t-test over its
     independent errors (the heading windows) of ``e_old^2 - e_new^2``, level ``alpha / K``.
     A few windows' RMS moves by several per cent by chance; the test keeps an effect from
     passing on that;

   where the residual sums are of *prewhitened* residuals ``w_i = r_i - rho r_(i-1)``
   (Cochrane & Orcutt 1949) and ``n_f``, ``n_s`` their counts, so that correlated residuals do
   not count as independent evidence: dead-reckoning errors are close to a random walk
   (``rho`` near 1, the test runs on increments), sensor noise is white (``rho`` near 0).
   ``rho`` is the noise autocorrelation of the fit-part residual of the *full* model (every
   candidate at once), like the full-model variance of Mallows' Cp, estimated from first
   differences (so slow structure that no candidate explains is not mistaken for correlated
   noise), or the plain estimate where that is lower by three standard errors (so noise that
   is no AR(1), a rate differenced from a noisy heading, is not mistaken for a random walk;
   :func:`koala_bridge.calibration.problem.lag1_autocorrelation`);
3. the passing candidate with the largest held-out statistic ``L`` is added; repeat until none
   passes (or ``max_effects``).

Heavy-tailed streams (:meth:`StreamProblem.robust_scale`, :mod:`koala_bridge.calibration.robust`)
are fitted with a soft-L1 loss of scale 1.4826 MAD. With a mixture effect in the model
(``outlier``: a share of spurious readings) the fit is EM (:func:`_fit_mixture`) and candidates
are judged by the same three tests on log-likelihoods with the fit part's parameters
(:func:`_judge_likelihood`): every reading counts, none is dropped, so *after* is not flattered.

Because the held-out part was not used to fit, an effect that only fits noise makes the held-out
RSS larger on average: the test is one-sided and conservative.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.problem import FloatArray, StreamProblem, split_params
from koala_bridge.calibration.robust import (
    gaussian_logpdf,
    inlier_responsibility,
    mad_sigma,
    mixture_loglik,
    weighted_rms,
)
from koala_bridge.core.distributions import chi2_ppf, f_sf, t_ppf
from numpy.typing import NDArray
from scipy import optimize

log = logging.getLogger(__name__)

ALPHA = 0.01
MIN_RELATIVE_GAIN = 0.01
MAX_EFFECTS = 6
#: EM (mixture effects): iterations at most, and the stop when the fit part's log-likelihood
#: rises by less than this per reading
EM_MAX_ITERATIONS = 30
EM_TOLERANCE = 1e-7
#: the largest spurious fraction EM may reach: beyond one half the "outliers" are the model
MAX_SPURIOUS_FRACTION = 0.5


@dataclass
class Fit:
    """A fitted model: its instances, parameter vector and residual sums."""

    insts: list[EffectInstance]
    x: FloatArray
    r_fit: FloatArray
    r_score: FloatArray
    jac: FloatArray | None = None
    #: unrounded residuals, when the model holds an output transform (quantisation)
    smooth: tuple[FloatArray, FloatArray] | None = None
    #: with a mixture effect: log density of a spurious reading per reading, (fit, score)
    log_g: tuple[FloatArray, FloatArray] | None = None
    #: with a mixture effect: (spurious fraction p, inlier sigma)
    mixture: tuple[float, float] | None = None
    #: with a mixture effect: the slice of ``x`` its parameters hold (EM's, not least squares';
    #: ``jac`` has no columns for them)
    em_slice: slice | None = None
    #: the declared relative noise level per reading, (fit, score) (StreamProblem.noise_shape)
    shape: tuple[FloatArray | None, FloatArray | None] = (None, None)
    #: the soft-L1 loss's scale when the fit used one (a heavy-tailed stream)
    robust_scale: float | None = None

    @property
    def rss_fit(self) -> float:
        return float(np.sum(self.r_fit**2))

    def loglik(self) -> tuple[float, float]:
        """Log-likelihood of the fit and the score part with the parameters of the fit part:
        the mixture's (module docstring), or Gaussian with the fit part's ML variance."""
        sf, ss = self.shape
        if self.mixture is not None and self.log_g is not None:
            p, sigma = self.mixture
            return (
                mixture_loglik(self.r_fit, sigma, p, self.log_g[0], sf),
                mixture_loglik(self.r_score, sigma, p, self.log_g[1], ss),
            )
        z = self.r_fit if sf is None else self.r_fit / sf
        sigma = float(np.sqrt(np.mean(z**2))) if z.size else 0.0
        return (
            float(np.sum(gaussian_logpdf(self.r_fit, sigma, sf))),
            float(np.sum(gaussian_logpdf(self.r_score, sigma, ss))),
        )

    def inlier_weights(self) -> FloatArray | None:
        """Posterior inlier probability of each fit-part reading (None without a mixture)."""
        if self.mixture is None or self.log_g is None:
            return None
        p, sigma = self.mixture
        return inlier_responsibility(self.r_fit, sigma, p, self.log_g[0], self.shape[0])


@dataclass(frozen=True)
class FurtherGain:
    """A further metric's practical size (module docstring): its relative drop and the paired
    t statistic of the drop against its one-sided threshold."""

    metric: str
    gain: float
    t: float
    t_threshold: float

    @property
    def passed(self) -> bool:
        return bool(self.gain >= MIN_RELATIVE_GAIN and self.t > self.t_threshold)


def further_gain(metric: str, old: FloatArray, new: FloatArray, n_tests: int = 1) -> FurtherGain:
    """The relative drop ``1 - rms(new) / rms(old)`` of paired independent errors, and the
    one-sided paired t-test of ``old^2 - new^2`` at level ``ALPHA / n_tests`` (Bonferroni over
    a round's candidates, as the likelihood-ratio test; nan below 3 pairs)."""
    if old.shape != new.shape:
        raise ValueError(f"{metric}: {old.size} errors before, {new.size} after: not paired")
    n = old.size
    if n < 3 or not np.all(np.isfinite(old)) or not np.all(np.isfinite(new)):
        return FurtherGain(metric, np.nan, np.nan, np.nan)
    ss_old, ss_new = _ss(old), _ss(new)
    gain = 1 - np.sqrt(ss_new / ss_old) if ss_old > 0 else np.nan
    d = old**2 - new**2
    mean, sd = float(np.mean(d)), float(np.std(d, ddof=1))
    if sd > 0:
        t = mean / (sd / np.sqrt(n))
    else:  # the same change in every window: certain, whichever way it goes
        t = float(np.sign(mean)) * np.inf if mean != 0 else np.nan
    return FurtherGain(metric, float(gain), t, t_ppf(1 - ALPHA / max(n_tests, 1), n - 1))


@dataclass
class Trial:
    """One candidate tried in one round, with the statistics of the stopping rule."""

    name: str
    k: int
    delta_bic: float
    lr: float
    lr_threshold: float
    relative_gain: float
    passed: bool
    fit: Fit | None = None
    #: fitted outside its physical range (:meth:`Effect.plausible`): rejected whatever its
    #: statistics
    implausible: bool = False
    #: the further metric, when it was asked for the practical size
    further: FurtherGain | None = None
    #: evidence of another test than the stopping rule's, reported in place of its statistics
    #: (a declared turn-on bias's z test: pipeline._turn_on_bias_check)
    other_test: dict[str, Any] | None = None

    def evidence(self) -> dict[str, Any]:
        if self.other_test is not None:
            return {**self.other_test, "n_params": self.k}
        out: dict[str, Any] = {
            "delta_bic_fit": _r(self.delta_bic),
            "heldout_lr": _r(self.lr),
            "heldout_lr_threshold": _r(self.lr_threshold),
            "heldout_relative_gain": _r(self.relative_gain),
            "n_params": self.k,
        }
        if self.further is not None:
            f = self.further
            out["heldout_further"] = {
                "metric": f.metric,
                "relative_gain": _r(f.gain),
                "paired_t": _r(f.t),
                "paired_t_threshold": _r(f.t_threshold),
            }
        return out


@dataclass
class Selection:
    """Result of the loop for one stream."""

    problem: StreamProblem
    before: Fit
    after: Fit
    added: list[tuple[EffectInstance, Trial]] = field(default_factory=list)
    rounds: list[list[Trial]] = field(default_factory=list)
    rho: float = 0.0
    #: the independent units of the fit and held-out parts where the stream counts them
    #: (:meth:`StreamProblem.independent_count`; then they, not ``rho``, give effective sizes)
    units: tuple[float | None, float | None] = (None, None)

    def params_of(self, fit: Fit) -> list[FloatArray]:
        return split_params(self.problem, fit.insts, fit.x)


def _r(v: float) -> float:
    return float(f"{v:.6g}") if np.isfinite(v) else float(v)


def _least_squares(
    problem: StreamProblem,
    insts: list[EffectInstance],
    x: FloatArray,
    weights: FloatArray | None = None,
    f_scale: float | None = None,
    max_nfev: int = 200,
    hold: slice | None = None,
) -> tuple[FloatArray, FloatArray | None]:
    """``(x, jac)`` of least squares on the fit part: weighted (EM's M step) when ``weights``
    are given, with a soft-L1 loss of scale ``f_scale`` when one is given; the entries of ``x``
    in ``hold`` (a mixture's, EM's own) are held and have no Jacobian column."""
    keep = np.ones(x.size, dtype=bool)
    if hold is not None:
        keep[hold] = False
    if not keep.any():
        return x, None
    sw = None if weights is None else np.sqrt(weights)
    full = x.copy()

    def fun(v: FloatArray) -> FloatArray:
        full[keep] = v
        r = problem.residuals(insts, full, "fit", for_fit=True)
        return r if sw is None else sw * r

    try:
        sol = optimize.least_squares(
            fun,
            x[keep],
            x_scale="jac",
            method="trf",
            max_nfev=max_nfev,
            loss="soft_l1" if f_scale else "linear",
            f_scale=f_scale or 1.0,
        )
    except ValueError as e:  # degenerate data (e.g. no samples): keep the start values
        log.warning("%s: fit of %s failed: %s", problem.name, [i.name for i in insts], e)
        return x, None
    out = x.copy()
    out[keep] = sol.x
    return out, sol.jac


def _param_slice(problem: StreamProblem, insts: Sequence[EffectInstance], at: int) -> slice:
    """The slice of the packed parameter vector holding ``insts[at]``'s free parameters."""
    k = len(problem.nuisance_x0()) + sum(i.n_free for i in insts[:at])
    return slice(k, k + insts[at].n_free)


def _fit_mixture(
    problem: StreamProblem, insts: list[EffectInstance], x0: FloatArray, at: int
) -> tuple[FloatArray, FloatArray | None]:
    """EM for a model whose instance ``insts[at]`` is a mixture effect: the spurious fraction
    ``p``, the inlier sigma and the model's other parameters jointly, maximising the fit part's
    mixture likelihood (:mod:`koala_bridge.calibration.robust`). Starts from a soft-L1 fit (so
    the spurious readings do not pull the start), then alternates responsibilities (E) with
    ``p``, ``sigma`` and a weighted least-squares refit (M) until the likelihood stops rising.
    The mixture's parameters (``p``, ``sigma``, its support) are its slice of ``x``; returns
    ``x`` and the Jacobian of the weighted residual (columns: every other parameter)."""
    mix = insts[at]
    em = _param_slice(problem, insts, at)
    x = np.asarray(x0, dtype=float).copy()
    p, sigma = float(x[em][0]), float(x[em][1])
    y = problem.readings("fit")
    shape = problem.noise_shape("fit")
    s = np.ones_like(y) if shape is None else shape
    scale = problem.robust_scale() or mad_sigma(problem.residuals(insts, x, "fit"))
    x, jac = _least_squares(problem, insts, x, f_scale=scale or None, hold=em)
    r = problem.residuals(insts, x, "fit")
    sigma = mad_sigma(r / s) or max(sigma, 1e-12)

    def log_g(r: FloatArray) -> FloatArray:
        return mix.effect.log_density(mix, x[em], y, r)

    prev = -np.inf
    lg = log_g(r)
    for _ in range(EM_MAX_ITERATIONS):
        w = inlier_responsibility(r, sigma, p, lg, shape)
        p = float(np.clip(1.0 - np.mean(w), 1e-6, MAX_SPURIOUS_FRACTION))
        sigma = max(weighted_rms(r / s, w), 1e-12)
        x[em.start], x[em.start + 1] = p, sigma
        if x.size > em.stop - em.start:
            x, jac = _least_squares(problem, insts, x, weights=w / s**2, max_nfev=50, hold=em)
            r = problem.residuals(insts, x, "fit")
            lg = log_g(r)       # (the log density depends on the residual, not on p or sigma)
        ll = mixture_loglik(r, sigma, p, lg, shape)
        if ll - prev < EM_TOLERANCE * max(r.size, 1):
            break
        prev = ll
    return x, jac


def _evaluated(
    problem: StreamProblem, insts: Sequence[EffectInstance], x: FloatArray, em: slice | None
) -> dict[str, Any]:
    """The :class:`Fit` fields that follow from the parameters ``x``: residuals, the unrounded
    ones with an output transform, and with a mixture effect (its parameters ``x[em]``) each
    reading's spurious log density and ``(p, sigma)``."""
    r_fit = problem.residuals(insts, x, "fit")
    r_score = problem.residuals(insts, x, "score")
    log_g = mixture = None
    if em is not None:
        mix = next(i for i in insts if i.effect.mixture)
        log_g = (
            mix.effect.log_density(mix, x[em], problem.readings("fit"), r_fit),
            mix.effect.log_density(mix, x[em], problem.readings("score"), r_score),
        )
        mixture = (float(x[em][0]), float(x[em][1]))
    smooth = None
    if any(i.effect.output_transform for i in insts):
        smooth = (
            problem.residuals(insts, x, "fit", for_fit=True),
            problem.residuals(insts, x, "score", for_fit=True),
        )
    return {"x": x, "r_fit": r_fit, "r_score": r_score, "smooth": smooth, "log_g": log_g,
            "mixture": mixture, "em_slice": em}


def at_values(problem: StreamProblem, fit: Fit, x: FloatArray) -> Fit:
    """``fit`` moved to the parameters ``x`` without refitting: what follows from them
    recomputed (:func:`_evaluated`); its Jacobian kept, for the standard errors (a parameter
    held at a bound: to first order what a fit with that bound gives the others)."""
    return replace(fit, **_evaluated(problem, fit.insts, x, fit.em_slice))


def fit_model(problem: StreamProblem, insts: Sequence[EffectInstance], x0: FloatArray) -> Fit:
    """Fit of all free parameters on the fit part: least squares; with a soft-L1 loss when the
    stream is heavy-tailed (:meth:`StreamProblem.robust_scale`); EM with a mixture effect."""
    insts = list(insts)
    x = np.asarray(x0, dtype=float)
    at = next((k for k, i in enumerate(insts) if i.effect.mixture), None)
    robust = None
    if at is not None:
        x, jac = _fit_mixture(problem, insts, x, at)
    else:
        robust = problem.robust_scale()
        x, jac = _least_squares(problem, insts, x, f_scale=robust)
        if not x.size:
            robust = None
    em = None if at is None else _param_slice(problem, insts, at)
    return Fit(insts=insts, jac=jac, robust_scale=robust,
               shape=(problem.noise_shape("fit"), problem.noise_shape("score")),
               **_evaluated(problem, insts, x, em))


def parameter_se(problem: StreamProblem, fit: Fit) -> FloatArray:
    """Standard errors of the free parameters: ``(J^T J)^-1`` times the stream's variance per
    residual (:meth:`StreamProblem.se_variance`: inflated for correlated residuals)."""
    if fit.em_slice is not None:
        return _mixture_se(problem, fit)
    if fit.jac is None or fit.x.size == 0:
        return np.zeros(fit.x.size)
    n = fit.r_fit.size
    s2 = problem.se_variance("fit", fit.r_fit, fit.rss_fit, fit.x.size)
    if fit.robust_scale is not None:
        # the sandwich sums the squared residuals itself: only the inflation over rss / n
        return _sandwich_se(problem, fit, fit.robust_scale,
                            s2 * n / fit.rss_fit if fit.rss_fit > 0 else 1.0)
    try:
        se = np.sqrt(np.clip(np.diag(np.linalg.pinv(fit.jac.T @ fit.jac) * s2), 0, None))
    except np.linalg.LinAlgError:
        se = np.full(fit.x.size, np.nan)
    labels = problem.clusters("fit")
    if labels is not None and labels.size == n and fit.jac.shape[0] == n:
        # the larger of the clusters' jackknife and the AR(1) count: each is too small where
        # the other is not (a few windows of unequal weight; a few glitches in the reference)
        return np.asarray(np.fmax(_cluster_se(fit, labels), se), dtype=float)
    return np.asarray(se, dtype=float)


def _cluster_se(fit: Fit, labels: NDArray[np.intp]) -> FloatArray:
    """Cluster-robust standard errors by the linearised jackknife over clusters (CR3; MacKinnon
    & Webb 2018, Pustejovsky & Tipton 2018): residuals within a cluster may be correlated in any
    way (a dead reckoning's window, whose errors grow from its start), clusters independent.
    Leaving cluster ``g`` out moves the parameters by ``(H - H_g)^-1 J_g^T r_g`` to first order
    (``H = J^T J``, ``H_g`` its share); the variance is ``(G-1)/G`` times the spread of those
    moves. With few clusters of unequal weight (the windows that turn carry a wheel base) the
    sandwich ``H^-1 (sum s_g s_g^T) H^-1`` (CR1) is too small: 1.7 times, over 40 seeds of
    120 s (15 windows); the jackknife weighs each window by what it alone decides. No more
    clusters than parameters and one (``G <= p + 1``) give no estimate (NaN: uncertain).

    No lag-1 autocorrelation stands in for the count: on a mower's odometry it read 0.999 for a
    smooth error (a time offset's SE 0.065 s) and 0.04 with 0.4 % of glitches in the reference
    (0.002 s), where the spread over segments gave 0.03."""
    assert fit.jac is not None
    jac = np.asarray(fit.jac, dtype=float)
    n, p = jac.shape
    _, g = np.unique(labels, return_inverse=True)
    groups = int(g.max()) + 1 if g.size else 0
    if groups <= p + 1 or n <= p:
        return np.full(fit.x.size, np.nan)
    h = jac.T @ jac
    # each cluster's share of H and its score, by bincount (a 1-hour odometry stream has 720
    # windows over 430 000 residuals: a mask per window cost 0.15 s)
    h_g = np.empty((groups, p, p))
    for a in range(p):
        for b in range(a, p):
            h_g[:, a, b] = h_g[:, b, a] = np.bincount(g, jac[:, a] * jac[:, b], groups)
    score = np.column_stack([np.bincount(g, jac[:, a] * fit.r_fit, groups) for a in range(p)])
    moves = np.einsum("gab,gb->ga", np.linalg.pinv(h[None] - h_g), score)
    moves -= moves.mean(axis=0)
    cov = (groups - 1) / groups * (moves.T @ moves)
    return np.sqrt(np.clip(np.diag(cov), 0, None))


def _mixture_se(problem: StreamProblem, fit: Fit) -> FloatArray:
    """Standard errors of a mixture fit: the other parameters from the Jacobian of the
    weighted residual with the inliers' variance; ``p`` binomial, ``sqrt(p (1 - p) / n_f)``;
    sigma ``sigma / sqrt(2 n_inliers)``; the support is declared, not fitted (0)."""
    assert fit.em_slice is not None and fit.mixture is not None
    se = np.zeros(fit.x.size)
    em = fit.em_slice
    w = fit.inlier_weights()
    p, sigma = fit.mixture
    n_in = float(np.sum(w)) if w is not None else float(fit.r_fit.size)
    se[em.start] = np.sqrt(p * (1 - p) / max(fit.r_fit.size, 1))
    se[em.start + 1] = sigma / np.sqrt(2 * max(n_in, 1.0))
    keep = np.ones(fit.x.size, dtype=bool)
    keep[em] = False
    if fit.jac is not None and keep.any() and w is not None:
        z = fit.r_fit if fit.shape[0] is None else fit.r_fit / fit.shape[0]
        s2 = float(np.sum(w * z**2)) / max(n_in - int(keep.sum()), 1.0)
        try:
            cov = np.linalg.pinv(fit.jac.T @ fit.jac) * s2
            se[keep] = np.sqrt(np.clip(np.diag(cov), 0, None))
        except np.linalg.LinAlgError:
            se[keep] = np.nan
    return se


def _sandwich_se(problem: StreamProblem, fit: Fit, c: float, inflation: float) -> FloatArray:
    """Standard errors of a soft-L1 fit (M-estimator, Huber 1967): ``H^-1 M H^-1`` with ``H``
    the cost's Gauss-Newton Hessian and ``M = sum psi_i^2 J_i J_i^T``. scipy returns the
    Jacobian scaled so that ``J~^T J~ = H``: for soft-L1 (``rho(z) = 2 (sqrt(1 + z) - 1)``,
    ``z = (r / c)^2``) its rows are ``J_i (1 + z_i)^(-3/4)`` and ``psi_i = r_i / sqrt(1 + z_i)``,
    so ``M = sum r_i^2 sqrt(1 + z_i) J~_i J~_i^T``."""
    assert fit.jac is not None
    r = problem.residuals(fit.insts, fit.x, "fit", for_fit=True)
    jt = np.asarray(fit.jac, dtype=float)
    if jt.shape[0] != r.size:
        return np.full(fit.x.size, np.nan)
    q = r**2 * np.sqrt(1.0 + (r / c) ** 2)
    try:
        h_inv = np.linalg.pinv(jt.T @ jt)
    except np.linalg.LinAlgError:
        return np.full(fit.x.size, np.nan)
    cov = h_inv @ ((jt * q[:, None]).T @ jt) @ h_inv * inflation
    return np.sqrt(np.clip(np.diag(cov), 0, None))


def prewhiten(r: FloatArray, rho: float) -> FloatArray:
    """AR(1) prewhitening ``r_i - rho r_(i-1)``."""
    return r[1:] - rho * r[:-1] if rho > 0 and r.size > 1 else r


def _ss(v: FloatArray) -> float:
    return float(np.dot(v, v))


#: Non-stationary noise (:func:`variance_blocks`): contiguous blocks of at least
#: VARIANCE_BLOCK_ROWS residuals, at most VARIANCE_BLOCKS of them; their spreads differ when the
#: Brown-Forsythe test rejects one at VARIANCE_ALPHA
VARIANCE_BLOCKS = 20
VARIANCE_BLOCK_ROWS = 50
VARIANCE_ALPHA = 1e-3


def variance_blocks(r: FloatArray) -> NDArray[np.intp] | None:
    """The starts of contiguous blocks of ``r`` whose spreads differ beyond chance, or None when
    one spread holds (:func:`brown_forsythe` about the blocks' medians, at
    ``VARIANCE_ALPHA``: robust to heavy tails, where Bartlett's test, which assumes
    normal residuals, rejected one variance on 213 of 300 t5 series and all t3 ones). A gyro
    that vibrates while its motors run has a residual several times noisier there than at rest,
    and a likelihood that counts every residual alike lets the noisy stretch drown what the
    quiet one shows (a still gyro's bias, 94 times chance on a quiet held-out part, failed the
    fit part's BIC beside 250 s of vibration)."""
    n = r.size
    b = min(VARIANCE_BLOCKS, n // VARIANCE_BLOCK_ROWS)
    if b < 2 or not np.all(np.isfinite(r)):
        return None
    starts = (np.arange(b) * n) // b
    if np.any(np.add.reduceat(r * r, starts) <= 0):
        return None
    p = brown_forsythe(np.split(r, starts[1:]))
    return starts if np.isfinite(p) and p < VARIANCE_ALPHA else None


def brown_forsythe(groups: Sequence[FloatArray]) -> float:
    """The Brown-Forsythe test's p-value (M. B. Brown & A. B. Forsythe 1974): the one-way
    analysis of variance of ``|x - median|`` within each group, ``scipy.stats.levene`` with
    ``center="median"`` (to 1e-12, ``tests/unit/test_calibration_vibration.py``) without
    importing ``scipy.stats`` (``core.distributions``); NaN where no group has any spread."""
    k = len(groups)
    z = [np.abs(g - np.median(g)) for g in groups]
    n = np.array([g.size for g in z], dtype=float)
    total = float(n.sum())
    means = np.array([float(np.mean(g)) for g in z])
    grand = float(np.dot(n, means) / total)
    within = float(sum(float(np.sum((g - m) ** 2)) for g, m in zip(z, means, strict=True)))
    if not within > 0 or k < 2:
        return float("nan")
    f = (total - k) / (k - 1) * float(np.dot(n, (means - grand) ** 2)) / within
    return f_sf(f, k - 1, total - k)


def round_blocks(
    current: Fit, rho: float, counts: tuple[float | None, float | None]
) -> tuple[NDArray[np.intp] | None, NDArray[np.intp] | None]:
    """The blocks of one variance (:func:`variance_blocks`) of the current model's fit and
    held-out residuals, as :func:`judge` compares them (prewhitened, unless the stream counts
    its independent units): one test per round, not per candidate."""
    rf, rs = current.r_fit, current.r_score
    if current.smooth is not None:
        rf, rs = current.smooth
    if counts[0] is None or counts[1] is None:
        rf, rs = prewhiten(rf, rho), prewhiten(rs, rho)
    return variance_blocks(rf), variance_blocks(rs)


def _log_ratio(
    old: FloatArray, new: FloatArray, starts: NDArray[np.intp] | None = None
) -> float:
    """``n ln(RSS_old / RSS_new)``, the log-likelihood ratio of Gaussian residuals of one
    variance; where ``old``'s variance differs between blocks (``starts``, of
    :func:`variance_blocks`), the sum over the blocks of theirs, each with its own variance."""
    tiny = 1e-300
    if starts is None:
        return max(old.size, 1) * float(np.log(max(_ss(old), tiny) / max(_ss(new), tiny)))
    sizes = np.diff(np.r_[starts, old.size])
    so = np.add.reduceat(old * old, starts)
    sn = np.add.reduceat(new * new, starts)
    if np.any(sn <= 0):  # a block the new model fits exactly (quantised readings): one variance
        return max(old.size, 1) * float(np.log(max(_ss(old), tiny) / max(_ss(new), tiny)))
    return float(np.dot(sizes, np.log(so / sn)))


def judge(
    old: Fit,
    new: Fit,
    k: int,
    n_candidates: int,
    rho: float,
    counts: tuple[float | None, float | None] = (None, None),
    blocks: tuple[NDArray[np.intp] | None, NDArray[np.intp] | None] | None = None,
) -> Trial:
    """Apply the stopping rule of the module docstring to one candidate; ``blocks``: for a
    stream whose noise may change over time (a rate stream: a gyro vibrating while its motors
    run), the fit and held-out parts' blocks of one variance (:func:`round_blocks`, None for a
    part of one variance), whose residual likelihoods are then summed per block
    (:func:`_log_ratio`)."""
    name = new.insts[-1].name
    if old.r_score.size == 0 or new.r_fit.size == 0:
        return Trial(name, k, np.nan, np.nan, np.nan, np.nan, False, new)
    if old.mixture is not None or new.mixture is not None:
        return _judge_likelihood(old, new, k, n_candidates, rho)
    tiny = 1e-300
    rf_old, rs_old, rf_new, rs_new = old.r_fit, old.r_score, new.r_fit, new.r_score
    if old.smooth is not None and new.smooth is not None:
        # Both round their output: compare the unrounded residuals (Effect.output_transform).
        (rf_old, rs_old), (rf_new, rs_new) = old.smooth, new.smooth
    wf_old, wf_new = prewhiten(rf_old, rho), prewhiten(rf_new, rho)
    ws_old, ws_new = prewhiten(rs_old, rho), prewhiten(rs_new, rho)
    nf, ns = max(wf_new.size, 1), max(ws_new.size, 1)
    if counts[0] is not None and counts[1] is not None:
        # The stream knows its independent units (odometry windows, heading-space windows):
        # raw sums, those counts.
        wf_old, wf_new, ws_old, ws_new = rf_old, rf_new, rs_old, rs_new
        nf, ns = max(counts[0], 1.0), max(counts[1], 1.0)
    if blocks is not None:
        # each residual's evidence at the count's rate: n ln(RSS ratio) is count * mean ln
        dbic = -_log_ratio(wf_old, wf_new, blocks[0]) * nf / max(wf_old.size, 1) \
            + k * np.log(nf)
        lr = _log_ratio(ws_old, ws_new, blocks[1]) * ns / max(ws_old.size, 1)
    else:
        dbic = nf * np.log(max(_ss(wf_new), tiny) / max(_ss(wf_old), tiny)) + k * np.log(nf)
        lr = ns * np.log(max(_ss(ws_old), tiny) / max(_ss(ws_new), tiny))
    thr = chi2_ppf(1 - ALPHA / max(n_candidates, 1), max(k, 1))
    ss_old, ss_new = _ss(rs_old), _ss(rs_new)
    gain = 1 - np.sqrt(ss_new / ss_old) if ss_old > 0 else 0.0
    passed = bool(dbic < 0 and lr > thr and gain >= MIN_RELATIVE_GAIN)
    return Trial(name, k, float(dbic), float(lr), thr, float(gain), passed, new)


def _judge_likelihood(old: Fit, new: Fit, k: int, n_candidates: int, rho: float) -> Trial:
    """The stopping rule when either model is a mixture (``outlier``): the same three tests on
    log-likelihoods with the fit part's parameters instead of residual sums. For Gaussian models
    with the variance profiled on the same part ``-2 dl = n ln(RSS_new / RSS_old)``, so the
    statistics keep their meaning: BIC
    ``-2 (l_f,new - l_f,old) + k ln n_f``; held-out ``L = 2 (l_s,new - l_s,old)`` against the
    same chi-square quantile; practical size ``1 - exp(-(l_s,new - l_s,old) / n_s)``, the drop of
    the geometric mean held-out density's scale (``1 - sqrt(RSS_new / RSS_old)`` for Gaussians).
    Every reading counts, spurious ones by their probability under the mixture: no reading is
    excluded. Correlated residuals: the statistics are scaled by ``(1 - rho) / (1 + rho)``
    (:func:`koala_bridge.calibration.problem.effective_size`)."""
    name = new.insts[-1].name
    lf_old, ls_old = old.loglik()
    lf_new, ls_new = new.loglik()
    nf, ns = max(new.r_fit.size, 1), max(new.r_score.size, 1)
    c = (1 - rho) / (1 + rho) if rho > 0 else 1.0
    dbic = -2 * c * (lf_new - lf_old) + k * np.log(max(c * nf, 2.0))
    lr = 2 * c * (ls_new - ls_old)
    thr = chi2_ppf(1 - ALPHA / max(n_candidates, 1), max(k, 1))
    gain = float(-np.expm1(-(ls_new - ls_old) / ns)) if np.isfinite(ls_new - ls_old) else np.nan
    passed = bool(dbic < 0 and lr > thr and gain >= MIN_RELATIVE_GAIN)
    return Trial(name, k, float(dbic), float(lr), thr, gain, passed, new)


def _practical_by_further(
    problem: StreamProblem, old: Fit, trial: Trial, n_candidates: int
) -> None:
    """Pass ``trial`` on the further metric's practical size (module docstring) when it
    failed on the practical size alone: significant on the fit and held-out parts, and the
    stream's own held-out metric not worse."""
    new = trial.fit
    if (
        trial.passed
        or new is None
        or old.mixture is not None
        or new.mixture is not None
        or not (trial.delta_bic < 0 and trial.lr > trial.lr_threshold)
        or not trial.relative_gain > 0
    ):
        return
    errors = problem.further_errors((old.insts, old.x), (new.insts, new.x))
    if errors is not None:
        metric, before, after = errors
        trial.further = further_gain(metric, before, after, n_candidates)
        trial.passed = trial.further.passed


def heldout_score(problem: StreamProblem, fit: Fit, likelihood: bool = False) -> float:
    """How well ``fit`` predicts the held-out part, lower is better, for comparing fits of one
    stream after the selection (a backward check, before against after): the stream's held-out
    metric, or, when a mixture effect (``outlier``) is among the fits compared
    (``likelihood``), the held-out negative log-likelihood per reading with the fit part's
    parameters (:meth:`Fit.loglik`), the quantity :func:`_judge_likelihood` selected it by. The
    metric (the RMS of every reading) cannot judge an outlier effect: it leaves the prediction
    as it was and changes which readings the model expects."""
    if likelihood:
        return -fit.loglik()[1] / max(fit.r_score.size, 1)
    return float(problem.metric_value(fit.insts, fit.x, "score"))


def noise_structure(
    problem: StreamProblem, start: Fit, candidates: Sequence[EffectInstance]
) -> tuple[float, tuple[float | None, float | None]]:
    """Lag-1 autocorrelation of the fit-part residual of the model with every candidate, and
    the independent units of its fit and held-out residuals where the stream counts them
    (:meth:`StreamProblem.independent_count`)."""
    full = start
    if candidates:
        insts = list(candidates)
        full = fit_model(problem, insts, problem.initial_vector(insts, start.x, start.insts))
    counts = (problem.independent_count("fit", full.r_fit),
              problem.independent_count("score", full.r_score))
    return problem.autocorrelation(full.r_fit), counts


def select_effects(
    problem: StreamProblem,
    candidates: Sequence[EffectInstance],
    max_effects: int = MAX_EFFECTS,
    on_trial: Callable[[], Any] | None = None,
) -> Selection:
    """Run the greedy loop of the module docstring on one stream."""
    current = fit_model(problem, [], problem.nuisance_x0())
    result = Selection(problem, current, current)
    remaining = list(candidates)
    rho, counts = noise_structure(problem, current, remaining)
    result.rho, result.units = rho, counts
    # scalar streams compared sample by sample (not odometry's or heading space's windows)
    by_blocks = problem.kind == "scalar" and getattr(problem, "integrate_window_s", None) is None
    explained: set[str] = set()  # candidates whose implausible fit the notes explain (once)
    while remaining and len(result.added) < max_effects:
        trials: list[Trial] = []
        blocks = round_blocks(current, rho, counts) if by_blocks else None
        for cand in remaining:
            # One mixture at most: another spurious-reading model is tried *in place of* the
            # one in the model (outlier:uniform chosen first may give way to outlier:short once
            # glitch explains the max-range readings), judged like any candidate.
            keep = [i for i in current.insts if not (cand.effect.mixture and i.effect.mixture)]
            insts = [*keep, cand]
            x0 = problem.initial_vector(insts, current.x, current.insts)
            new = fit_model(problem, insts, x0)
            trial = judge(current, new, cand.effect.n_tested(cand), len(remaining), rho, counts,
                          blocks=blocks)
            _practical_by_further(problem, current, trial, len(remaining))
            *earlier, params = split_params(problem, new.insts, new.x)
            if not cand.effect.plausible(cand, params):
                trial.implausible = True
                would_pass, trial.passed = trial.passed, False
                if would_pass:
                    log.info("%s: %s fitted outside its physical range: rejected",
                             problem.name, cand.name)
                # said for what it is when fitted alone against the model so far, or when it
                # would otherwise have passed (later, another effect may have dragged it there)
                why = cand.effect.implausible_reason(cand, params, problem)
                if why and cand.name not in explained and (not result.added or would_pass):
                    explained.add(cand.name)
                    problem.notes.append(why)
            elif not all(i.effect.plausible(i, v)
                         for i, v in zip(new.insts[:-1], earlier, strict=True)):
                # the candidate drags an effect already in the model out of its range
                trial.passed = False
                trial.implausible = True
            trials.append(trial)
            if on_trial is not None:
                on_trial()
        result.rounds.append(trials)
        passing = [t for t in trials if t.passed]
        for t in trials:
            log.debug(
                "%s: %s dBIC=%.3g LR=%.3g/%.3g gain=%.3g%s",
                problem.name,
                t.name,
                t.delta_bic,
                t.lr,
                t.lr_threshold,
                t.relative_gain,
                " PASS" if t.passed else "",
            )
        if not passing:
            break
        best = max(passing, key=lambda t: t.lr)
        assert best.fit is not None
        current = best.fit
        chosen = current.insts[-1]
        if chosen.effect.mixture:  # replaced, not added: see the loop above
            result.added = [(i, t) for i, t in result.added if not i.effect.mixture]
        result.added.append((chosen, best))
        # each candidate enters once: a replaced mixture does not come back, so no cycles
        remaining = [c for c in remaining if c.name != chosen.name]
        log.info(
            "%s: added %s (held-out gain %.1f %%)",
            problem.name,
            chosen.name,
            100 * best.relative_gain,
        )
    result.after = current
    return result
