"""The few distribution functions the filters and the calibration need, from ``scipy.special``.

``scipy.stats`` builds every distribution object of its catalogue on import: ~0.5 s of a
command's start-up (``koala-bridge calibrate``, ``run`` with the localisation node) for five
numbers. ``scipy.stats`` computes these same quantities with the same ``scipy.special``
functions (its ``chi2._ppf``/``_isf``, ``norm._sf``/``_ppf``, ``t._ppf``, ``binom._sf``), so
the values are the same to the last bit or two (``tests/unit/test_distributions.py`` holds
them to 1e-12 of ``scipy.stats``).
"""

from __future__ import annotations

from scipy import special


def chi2_ppf(q: float, dof: float) -> float:
    """Quantile ``x`` of the chi-square distribution: ``P(X <= x) = q`` (``stats.chi2.ppf``)."""
    return float(2.0 * special.gammaincinv(0.5 * dof, q))


def norm_ppf(q: float) -> float:
    """Quantile of the standard normal distribution (``stats.norm.ppf``)."""
    return float(special.ndtri(q))


def t_ppf(q: float, dof: float) -> float:
    """Quantile of Student's t distribution with ``dof`` degrees of freedom (``stats.t.ppf``)."""
    return float(special.stdtrit(dof, q))


def norm_sf(z: float) -> float:
    """Upper tail ``P(Z > z)`` of the standard normal distribution (``stats.norm.sf``)."""
    return float(special.ndtr(-z))


def binom_sf(k: float, n: int, p: float) -> float:
    """Upper tail ``P(X > k)`` of the binomial distribution ``B(n, p)`` (``stats.binom.sf``)."""
    if k < 0:
        return 1.0
    if k >= n:
        return 0.0
    return float(special.bdtrc(k, n, p))


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """Upper tail ``P(F > x)`` of the F distribution (``stats.f.sf``)."""
    return float(special.fdtrc(dfn, dfd, x))
