"""Acceptance intervals for the statistical model tests, derived from the sampling distributions.

Every test runs at a fixed seed, so it is deterministic; the intervals say how far a correct model
may stray (two-sided, probability ALPHA of a false alarm per check) and each test also asserts
that a plausible wrong model would fall outside (``power``), so a check cannot pass vacuously.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

ALPHA = 1e-4


def binomial_interval(n: int, p: float, alpha: float = ALPHA) -> tuple[int, int]:
    """Counts [lo, hi] holding a Binomial(n, p) count with probability >= 1 - alpha."""
    return int(stats.binom.ppf(alpha / 2, n, p)), int(stats.binom.isf(alpha / 2, n, p))


def assert_rate(k: int, n: int, p: float, *, wrong: float | None = None,
                alpha: float = ALPHA) -> None:
    """Assert ``k`` successes in ``n`` Bernoulli(p) trials; and that p = ``wrong`` would fail."""
    lo, hi = binomial_interval(n, p, alpha)
    assert lo <= k <= hi, f"{k}/{n} = {k / n:.5f} outside [{lo}, {hi}] for p = {p:.5f}"
    if wrong is not None:
        wlo, whi = binomial_interval(n, wrong, alpha)
        assert hi < wlo or whi < lo, f"test cannot tell p={p} from p={wrong} with n={n}"


def chi2_variance_interval(n: int, sigma2: float, alpha: float = ALPHA) -> tuple[float, float]:
    """Interval for the sample variance (ddof=1) of ``n`` normal samples of variance sigma2:
    (n-1) s^2 / sigma^2 ~ chi^2(n-1)."""
    lo = stats.chi2.ppf(alpha / 2, n - 1) * sigma2 / (n - 1)
    hi = stats.chi2.isf(alpha / 2, n - 1) * sigma2 / (n - 1)
    return float(lo), float(hi)


def assert_normal_variance(x: np.ndarray, sigma2: float, *, wrong: float | None = None,
                           alpha: float = ALPHA, mean: float | None = None) -> None:
    """Assert the sample variance of normal samples ``x`` is consistent with ``sigma2``.

    With a known ``mean`` the statistic is sum((x - mean)^2)/sigma2 ~ chi^2(n)."""
    x = np.asarray(x, dtype=float).ravel()
    n = x.size
    if mean is None:
        s2 = float(np.var(x, ddof=1))
        lo, hi = chi2_variance_interval(n, sigma2, alpha)
        wlo, whi = (chi2_variance_interval(n, wrong, alpha) if wrong is not None else (0, 0))
    else:
        s2 = float(np.mean((x - mean) ** 2))
        lo, hi = chi2_variance_interval(n + 1, sigma2, alpha)
        wlo, whi = (chi2_variance_interval(n + 1, wrong, alpha) if wrong is not None else (0, 0))
    assert lo <= s2 <= hi, f"variance {s2:.6g} outside [{lo:.6g}, {hi:.6g}] for {sigma2:.6g}"
    if wrong is not None:
        assert hi < wlo or whi < lo, f"test cannot tell variance {sigma2} from {wrong}"


def assert_mean(x: np.ndarray, mu: float, sigma: float, *, alpha: float = ALPHA,
                wrong: float | None = None) -> None:
    """Assert the sample mean of ``x`` (i.i.d., std ``sigma``) is within the CLT interval of mu."""
    x = np.asarray(x, dtype=float).ravel()
    half = stats.norm.isf(alpha / 2) * sigma / math.sqrt(x.size)
    m = float(x.mean())
    assert abs(m - mu) <= half, f"mean {m:.6g} not within {mu:.6g} +- {half:.3g}"
    if wrong is not None:
        assert abs(wrong - mu) > 2 * half, f"test cannot tell mean {mu} from {wrong}"


def assert_uniform_counts(counts: np.ndarray, alpha: float = ALPHA) -> None:
    """Chi-square goodness of fit of bin counts to equal probabilities."""
    counts = np.asarray(counts, dtype=float)
    expected = counts.sum() / counts.size
    stat = float(((counts - expected) ** 2 / expected).sum())
    crit = stats.chi2.isf(alpha, counts.size - 1)
    assert stat <= crit, f"chi2 {stat:.2f} > {crit:.2f}: counts {counts} not uniform"
