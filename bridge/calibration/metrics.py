"""Summaries of held-out errors for the report: robust statistics and an honest before/after.

Pure functions of residual vectors (no problem, no model), so a known vector tests them.

* :func:`heldout_statistics`: RMS, median absolute error, 95th percentile of the absolute error
  and the outlier fraction of the held-out errors before and after, the outliers judged on one
  scale for both: the after-model's robust noise level (:func:`robust_sigma`).
* :func:`change`: the change of an error metric from before to after, always on magnitudes, so a
  signed metric whose sign flips (``+0.23 -> -0.24 rad``) reads as the worsening it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from koala_bridge.calibration.robust import MAD_TO_SIGMA
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: An error is an outlier when it lies beyond this many robust sigmas from its set's median.
OUTLIER_SIGMAS = 5.0
#: Percentile of the absolute error reported beside the RMS and the median.
PERCENTILE = 95.0


@dataclass(frozen=True)
class ErrorStatistics:
    """Summary of one model's held-out errors (in the stream's unit)."""

    rms: float
    median_abs: float
    p95_abs: float
    outlier_fraction: float

    def as_dict(self) -> dict[str, float | None]:
        return {
            "rms": _num(self.rms),
            "median_abs": _num(self.median_abs),
            "p95_abs": _num(self.p95_abs),
            "outlier_fraction": _num(self.outlier_fraction),
        }


@dataclass(frozen=True)
class HeldOutStatistics:
    """Held-out errors before and after, the outliers of both judged against ``threshold``
    (``OUTLIER_SIGMAS`` robust sigmas of the after-model's errors)."""

    n: int
    threshold: float
    before: ErrorStatistics
    after: ErrorStatistics


def _num(v: float) -> float | None:
    return float(f"{v:.6g}") if np.isfinite(v) else None


def g4(v: float) -> str:
    """A metric as the report and the notes print it: 4 significant digits, "-" for none."""
    return f"{v:.4g}" if np.isfinite(v) else "-"


def robust_sigma(r: FloatArray) -> float:
    """``1.4826 MAD``, MAD the median absolute deviation of ``r`` from its median: the standard
    deviation of the bulk of the errors, which a few gross ones do not move. When more than half
    the errors are equal (quantised readings, glitches scored 0) the MAD is 0; the standard
    deviation about the median is used then (0 only when every error is the same)."""
    r = np.asarray(r, dtype=float)
    if r.size == 0:
        return float("nan")
    med = float(np.median(r))
    mad = MAD_TO_SIGMA * float(np.median(np.abs(r - med)))
    return mad if mad > 0 else float(np.sqrt(np.mean((r - med) ** 2)))


def error_statistics(r: FloatArray, threshold: float) -> ErrorStatistics:
    """Statistics of one error vector; an outlier is ``|r - median(r)| > threshold``."""
    r = np.asarray(r, dtype=float)
    if r.size == 0:
        nan = float("nan")
        return ErrorStatistics(nan, nan, nan, nan)
    a = np.abs(r)
    outside = np.abs(r - np.median(r)) > threshold
    return ErrorStatistics(
        rms=float(np.sqrt(np.mean(r**2))),
        median_abs=float(np.median(a)),
        p95_abs=float(np.percentile(a, PERCENTILE)),
        outlier_fraction=float(np.mean(outside)),
    )


def heldout_statistics(before: FloatArray, after: FloatArray) -> HeldOutStatistics:
    """Statistics of the held-out errors of the declared (``before``) and the calibrated
    (``after``) model. Both sets' outliers are judged on the after-model's scale,
    ``OUTLIER_SIGMAS * robust_sigma(after)``, so the two fractions compare: how many held-out
    errors lie far beyond the noise the calibrated model leaves."""
    after = np.asarray(after, dtype=float)
    threshold = OUTLIER_SIGMAS * robust_sigma(after) if after.size else float("nan")
    return HeldOutStatistics(
        int(after.size),
        threshold,
        error_statistics(before, threshold),
        error_statistics(after, threshold),
    )


@dataclass(frozen=True)
class Change:
    """The change of an error metric's magnitude: ``relative`` = ``(|after| - |before|) /
    |before|`` (negative: smaller error), and the words for it."""

    relative: float
    text: str


def change(before: float, after: float) -> Change:
    """``better by 63 %``, ``worse by 4.3 %``, ``unchanged``: always of ``|before|`` and
    ``|after|``, since every metric is an error and a sign is no improvement."""
    b, a = abs(before), abs(after)
    if not (np.isfinite(b) and np.isfinite(a)):
        return Change(float("nan"), "not comparable (a value is missing)")
    if b == 0:
        return Change(0.0 if a == 0 else float("inf"), "unchanged" if a == 0 else "worse (from 0)")
    rel = (a - b) / b
    pct = 100 * abs(rel)
    if pct == 0:
        return Change(0.0, "unchanged")
    words = "better" if rel < 0 else "worse"
    return Change(rel, f"{words} by {pct:.2g} %" if pct < 10 else f"{words} by {pct:.0f} %")
