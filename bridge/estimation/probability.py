"""Probability <-> log-odds and normalisation in the log domain (seeds/003 "Key functions" A, F).

The lab writes the forward conversion as ``l = ln(1 / (1 - p))``; that is not the inverse of its
own backward conversion ``p = 1 - 1 / (1 + e^l)`` (a logistic). We use the pair that *is*
consistent, the log-odds ``l = ln(p / (1 - p))`` and its logistic inverse.
"""

from __future__ import annotations

import numpy as np
from koala_bridge.estimation.errors import EstimationError
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def log_odds(p: ArrayLike) -> FloatArray:
    """``ln(p / (1 - p))``; ``p = 0`` gives ``-inf`` and ``p = 1`` gives ``+inf``."""
    pa = np.asarray(p, dtype=float)
    with np.errstate(divide="ignore"):
        return np.log(pa) - np.log1p(-pa)


def prob_from_log_odds(lo: ArrayLike) -> FloatArray:
    """The logistic ``1 - 1 / (1 + e^l)`` (seeds/003 A, inverse), computed without overflow."""
    la = np.asarray(lo, dtype=float)
    return 0.5 * (1.0 + np.tanh(0.5 * la))


def log_normalise(log_w: FloatArray) -> FloatArray:
    """Shift unnormalised log-probabilities so that ``sum(exp(result)) == 1`` (seeds/003 F).

    ``-inf`` entries (impossible states, e.g. blocked cells) stay ``-inf``. Raises
    :class:`EstimationError` when every entry is ``-inf`` (the model and the data contradict).
    """
    m = float(np.max(log_w))
    if not np.isfinite(m):
        raise EstimationError("every state has zero probability; cannot normalise")
    return log_w - (m + float(np.log(np.sum(np.exp(log_w - m)))))
