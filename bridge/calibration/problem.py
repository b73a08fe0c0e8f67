"""The stream problem: what every stream (gyro, compass, odometry, ranges, ...) gives the loop.

A :class:`StreamProblem` predicts a stream's measurements from the reference with the declared
model plus a list of :class:`calibration.effects.EffectInstance`, and returns the residual
on the fit or the score part of the time split. Parameters of all instances are one vector:
``[nuisance..., free parameters of instance 1..., instance 2..., ...]``; nuisance parameters belong
to the declared model itself (a compass's unknown north direction, a field magnitude) and are
fitted in every model, including the one reported as *before*.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Part = Literal["fit", "score"]

#: Fraction of a stream's time span used for fitting; the rest is held out for scoring.
FIT_FRACTION = 0.6


@dataclass(frozen=True)
class Split:
    """Fit on ``[t0, t1)``, score on ``[t1, t2]`` (``t1 = t0 + 0.6 (t2 - t0)``)."""

    t0: float
    t1: float
    t2: float

    @classmethod
    def of(cls, t: FloatArray) -> Split:
        t0, t2 = float(np.min(t)), float(np.max(t))
        return cls(t0, t0 + FIT_FRACTION * (t2 - t0), t2)

    def mask(self, t: FloatArray, part: Part) -> NDArray[np.bool_]:
        return (t < self.t1) if part == "fit" else (t >= self.t1)


@dataclass(frozen=True)
class SecondaryMetric:
    """A further metric of the same stream, reported as its own entry of report.json."""

    metric: str
    unit: str
    before: float
    after: float
    #: the metric can be negative (a signed error, e.g. ``known_rotation_error``): reported by
    #: its magnitude, the signed values beside it (report.py)
    signed: bool = False


@dataclass(frozen=True)
class SkippedStream:
    """A stream of the bundle that could not be calibrated: what it lacks and how to add it.

    ``missing`` and ``fix`` are read together, as in the report's line
    ``range:ir: true_range is empty in every row: add true_range (m) per row, ...``.
    """

    stream: str
    missing: str
    fix: str

    def line(self) -> str:
        return f"{self.stream}: {self.missing}: {self.fix}"


#: Fewest usable rows a stream is calibrated on: both the fit and the held-out part need data.
MIN_ROWS = 10
#: Where a bundle's files and columns are described, for the report's "how to add it".
FORMAT_DOC = "docs/bundle-format.md"


def skip_stream(skipped: list[SkippedStream] | None, stream: str, missing: str, fix: str) -> None:
    """Record that ``stream`` cannot be calibrated; the report and the CLI say so."""
    logging.getLogger(__name__).debug("%s not calibrated: %s", stream, missing)
    if skipped is not None:
        skipped.append(SkippedStream(stream, missing, fix))


@dataclass
class StreamProblem(ABC):
    """Base of the per-stream problems in :mod:`koala_bridge.calibration.streams`."""

    name: str
    kind: str
    metric: str
    unit: str
    section: str
    split: Split
    notes: list[str] = field(default_factory=list, kw_only=True)
    #: effect name -> config key of the stream's own section that the effect sets (the total,
    #: declared value plus what was found); effects without one write ``calibration.<name>``.
    native_keys: dict[str, str] = field(default_factory=dict, kw_only=True)
    #: effect name -> the declared value the found parameter adds to.
    declared_values: dict[str, Any] = field(default_factory=dict, kw_only=True)

    # ----- the model -------------------------------------------------------------------------
    def nuisance_x0(self) -> FloatArray:
        """Starting values of the declared model's nuisance parameters (default: none)."""
        return np.empty(0)

    def initial_vector(
        self,
        insts: Sequence[EffectInstance],
        previous: FloatArray | None = None,
        previous_insts: Sequence[EffectInstance] = (),
    ) -> FloatArray:
        """Parameter vector for ``insts``, warm-started from a previous fit where names match."""
        parts = [self.nuisance_x0() if previous is None else previous[: len(self.nuisance_x0())]]
        prev = (
            dict(
                zip(
                    [i.name for i in previous_insts],
                    split_params(self, previous_insts, previous),
                    strict=True,
                )
            )
            if previous is not None
            else {}
        )
        for inst in insts:
            if inst.fixed:
                continue
            parts.append(np.asarray(prev.get(inst.name, inst.x0), dtype=float))
        return np.concatenate(parts) if parts else np.empty(0)

    @abstractmethod
    def residuals(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: Part, for_fit: bool = False
    ) -> FloatArray:
        """Residual vector (measured - predicted, in :attr:`unit`) on one part of the split.

        ``for_fit`` asks for the smooth version least squares minimises (no output rounding).
        """

    def metric_value(self, insts: Sequence[EffectInstance], x: FloatArray, part: Part) -> float:
        """The stream's reported metric; the default is the RMS of the residual."""
        r = self.residuals(insts, x, part)
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    def secondary_metrics(
        self,
        before: tuple[Sequence[EffectInstance], FloatArray],
        after: tuple[Sequence[EffectInstance], FloatArray],
    ) -> list[SecondaryMetric]:
        """Further metrics on the score part (default: none)."""
        return []

    def further_errors(
        self,
        old: tuple[Sequence[EffectInstance], FloatArray],
        new: tuple[Sequence[EffectInstance], FloatArray],
    ) -> tuple[str, FloatArray, FloatArray] | None:
        """A further held-out metric that may show an effect's practical size when the
        stream's own metric cannot (:mod:`koala_bridge.calibration.selection`): its name and
        its independent errors (one per unit, say per window) under ``old`` and ``new``, in
        the same order; default: none."""
        return None

    def heldout_errors(self, insts: Sequence[EffectInstance], x: FloatArray) -> FloatArray:
        """One error per held-out measurement, in :attr:`unit`, for the report's robust
        statistics (:mod:`koala_bridge.calibration.metrics`); default: the score residual."""
        return self.residuals(insts, x, "score")

    @abstractmethod
    def residual_series(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """``(t, r)`` over the whole span, for the residual plot (r: 1-D, one value per t)."""

    def autocorrelation(self, r: FloatArray) -> float:
        """Lag-1 autocorrelation of a residual vector in this stream's sample order."""
        return lag1_autocorrelation(r)

    def independent_count(self, part: Part, r: FloatArray | None = None) -> float | None:
        """Number of independent units in a part's residual (``r``, the model's, when the count
        depends on it) when the stream knows it better than an AR(1) model does (None:
        prewhiten and count residuals)."""
        return None

    def clusters(self, part: Part) -> NDArray[np.intp] | None:
        """The cluster of each residual of ``part`` where residuals share their errors in
        groups (a dead reckoning's window: every position in it carries the heading error of
        its start), for the parameters' cluster-robust standard errors
        (:func:`koala_bridge.calibration.selection.parameter_se`); None (the default): the
        residuals are counted by :meth:`se_variance`."""
        return None

    def se_variance(self, part: Part, r: FloatArray, rss: float, n_params: int) -> float:
        """The variance per residual that scales ``(J^T J)^-1`` into the parameters' covariance,
        for the residuals ``r`` of ``part`` (sum of squares ``rss``) of a fit of ``n_params``:
        ``rss / (n - p)``, inflated by ``n / n_eff`` for correlated residuals (the AR(1)
        correction, :func:`effective_size`)."""
        n = int(r.size)
        return rss / max(n - n_params, 1) * n / effective_size(n, self.autocorrelation(r))

    def readings(self, part: Part) -> FloatArray:
        """The measured value of each reading of ``part``, one per residual (the density of a
        spurious reading depends on it; streams without one reading per residual have none)."""
        raise NotImplementedError(f"{self.name}: no single reading per residual")

    def noise_shape(self, part: Part) -> FloatArray | None:
        """The declared relative noise level of each reading of ``part`` (a sonar's distance
        error grows with the range); None (the default): the same for every reading."""
        return None

    def robust_scale(self) -> float | None:
        """The robust noise scale (1.4826 MAD) of the declared model's fit-part residual when
        that residual is heavy-tailed (:func:`koala_bridge.calibration.robust.heavy_tailed`):
        least squares then uses a soft-L1 loss with this scale, so spurious readings cannot pull
        the parameters. None (the default): plain least squares."""
        return None

    def config_values(self, insts: Sequence[EffectInstance], x: FloatArray) -> dict[str, Any]:
        """Config keys written for the declared model's own fitted parts (default: none)."""
        return {}

    def noise_estimate(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[str | None, float | None]:
        """``(key, value)``: the white-noise level of the residual of ``insts`` in the
        simulator's noise key of this stream's section (default: none; see
        :func:`koala_bridge.calibration.config_update.noise_keys`)."""
        return None, None

    def describe(self) -> dict[str, Any]:
        """Facts about the stream for the report (sample counts, reference used, ...)."""
        return {}


class LastResult:
    """The last value a model evaluation returned for each part, kept while the same
    instances and parameter vector come again.

    The search, its backward check, the refit on the full stream and the report evaluate the
    same model with the same ``x`` several times in a row (``fit_model``'s residuals, then
    ``metric_value``, then the secondary metrics); on a 1-hour odometry stream each evaluation
    is a dead reckoning of 360 000 samples. Instances are compared by identity (they hold
    dicts, so they are not hashable) and held, so an id cannot be reused while its entry
    lives; ``x`` by its bytes. Callers must not modify a returned array.
    """

    def __init__(self) -> None:
        self._last: dict[str, tuple[tuple[EffectInstance, ...], bytes, Any]] = {}

    def get(self, insts: Sequence[EffectInstance], x: FloatArray, part: str) -> Any:
        hit = self._last.get(part)
        if hit is None or len(hit[0]) != len(insts) or hit[1] != np.asarray(x).tobytes():
            return None
        if any(a is not b for a, b in zip(hit[0], insts, strict=True)):
            return None
        return hit[2]

    def put(self, insts: Sequence[EffectInstance], x: FloatArray, part: str, value: Any) -> Any:
        self._last[part] = (tuple(insts), np.asarray(x).tobytes(), value)
        return value


def lag1_autocorrelation(r: FloatArray) -> float:
    """Lag-1 autocorrelation of the noise in ``r``, in [0, 0.999]: from the first differences,
    or the plain estimate where that is clearly lower (:data:`LAG1_DISAGREE_Z`): each is too
    large in a case the other is not.

    - From the first differences: for an AR(1) series with coefficient rho they have lag-1
      autocorrelation -(1 - rho) / 2, so rho = 1 + 2 rho_diff. Unlike the plain estimate it is
      not fooled by slow deterministic structure (an unexplained effect spanning many samples),
      which is not chance; a random walk (integrated noise, as in dead reckoning) still gives
      rho near 1.
    - The plain lag-1 autocorrelation. Noise that is no AR(1) fools the first: a rate
      differenced from a noisy heading, centred on the readings, is white noise's moving
      difference, whose own differences are about uncorrelated, so it read 0.999 where the
      residual's lag-1 autocorrelation is 0.26. Prewhitened at 0.999, a residual is its
      changes, and a smooth error no longer counts: a gyro reading 1.5 times the motion was
      given a time offset and no scale.
    """
    r = np.asarray(r, dtype=float).ravel()
    if r.size < 4:
        return 0.0
    d = np.diff(r)
    d = d - d.mean()
    den = float(np.dot(d, d))
    rho_d = float(np.dot(d[1:], d[:-1]) / den) if den > 0 else -0.5
    rho = 1.0 + 2.0 * rho_d
    c = r - r.mean()
    den = float(np.dot(c, c))
    plain = float(np.dot(c[1:], c[:-1]) / den) if den > 0 else 0.0
    if plain < rho - LAG1_DISAGREE_Z * 2.0 / np.sqrt(r.size):
        rho = plain  # clearly lower: the noise is no AR(1)
    return min(max(rho, 0.0), 0.999)


#: the plain lag-1 autocorrelation replaces the first differences' when it is lower by this many
#: of the latter's standard errors (``2 / sqrt(n)``): two noisy estimates' minimum would be
#: biased low (an AR(0.98) residual of 2400 read as 49 independent units, not 24)
LAG1_DISAGREE_Z = 3.0


def effective_size(n: int, rho: float) -> float:
    """n (1 - rho) / (1 + rho), at least 2: the AR(1) variance-inflation correction (e.g.
    Bretherton et al. 1999, J. Climate 12, eq. 31), so correlated residuals do not pass for many
    independent ones."""
    if n < 3:
        return float(n)
    return float(max(min(n * (1 - rho) / (1 + rho), n), 2.0))


def split_params(
    problem: StreamProblem, insts: Sequence[EffectInstance], x: FloatArray | None
) -> list[FloatArray]:
    """Per-instance parameter arrays from the packed vector (fixed instances: their ``x0``)."""
    out: list[FloatArray] = []
    if x is None:
        return [np.asarray(i.x0, dtype=float) for i in insts]
    k = len(problem.nuisance_x0())
    for inst in insts:
        if inst.fixed:
            out.append(np.asarray(inst.x0, dtype=float))
        else:
            out.append(np.asarray(x[k : k + inst.n_free], dtype=float))
            k += inst.n_free
    return out


def apply_all(
    state: Any, problem: StreamProblem, insts: Sequence[EffectInstance], x: FloatArray
) -> None:
    """Apply every instance's effect to a stream state, in order."""
    for inst, p in zip(insts, split_params(problem, insts, x), strict=True):
        inst.apply(state, p)
