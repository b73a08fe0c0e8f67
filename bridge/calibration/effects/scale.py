"""``scale``: a gain error of a scalar measurement.

    y = (1 + s) * gain * curve(u) + ...          params: s (dimensionless)

Writes the native scale key (gyro: ``[sensors.gyro] scale_factor_error`` = (1 + declared)(1 + s)
- 1) or
``[sensors.<stream>.calibration] scale``.

A gain is determined only where the reference ``u`` varies well beyond its own noise. Noise in
the reference pulls a least-squares gain towards zero by the noise's share of the reference's
variance, ``1 + s_fitted ~ (1 + s) var(u_true) / var(u)`` (regression dilution, errors in
variables: W. A. Fuller, *Measurement Error Models*, 1987, sec. 1.1). A gyro lying still
against the rate differentiated from an optical heading is the extreme: the reference is all
noise and the fitted gain goes to about 0 (``s`` ~ -1, a sensor that "reads nothing") with a
small standard error. So ``scale`` is proposed only when that share, estimated on the fit part
as the reference's fast variation the readings do not share
(:func:`.common.reference_noise_share`), is at most ``MAX_REFERENCE_NOISE_SHARE``
(:func:`.common.reference_dominates`); else a note says why, and above 1 % the report notes
that a fitted gain may be attenuated by it. A gain that is not positive (``1 + s <= 0``) is no
scale error of a working sensor: implausible. The noise share (in the space the stream is
compared in) bounds the dilution, ``share (1 + s)``; where that is more than ``WRITE_Z`` standard
errors, the value is biased beyond its uncertainty and not written (:meth:`estimate_bias`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.effects.common import (
    NOTE_REFERENCE_NOISE_SHARE,
    gain_share,
    reference_dominates,
    scalar_config,
)

#: a gain beyond this factor either way is a unit or a time base, not a sensor's error
GROSS_GAIN = 2.0
#: the factors a gain that large usually is, and what each says
GROSS_FACTORS = (
    (180 / np.pi, "degrees where radians are meant (deg/s for rad/s)"),
    (np.pi / 180, "radians where degrees are meant"),
    (1000.0, "a thousandfold unit (mm for m, mrad for rad) or a time base in ms"),
    (1e-3, "a thousandfold unit (m for mm) or a time base in ks"),
    (100.0, "cm where m are meant"),
    (0.01, "m where cm are meant"),
    (10.0, "a tenfold unit, or a time base of tenths of a second read as seconds"),
    (0.1, "a tenfold unit, or a time base ten times too fine"),
)


def gross_gain(gain: float) -> str | None:
    """What a gain beyond :data:`GROSS_GAIN` either way (by magnitude) most likely is: ``": 57.3
    is degrees where radians are meant ..."`` within 15 % of one of :data:`GROSS_FACTORS`, ``""``
    beyond that; None for a gain a sensor may have."""
    size = abs(gain)  # a sign is said apart (Scale.implausible_reason), a unit here
    if not (size > GROSS_GAIN or 0 < size < 1 / GROSS_GAIN):
        return None
    factor, says = min(GROSS_FACTORS, key=lambda f: abs(np.log(size / f[0])))
    return f": {factor:.4g} is {says}" if abs(np.log(size / factor)) < np.log(1.15) else ""


@register_effect("scale")
class Scale(Effect):
    kinds = frozenset({"scalar"})

    def _propose(self, problem: Any) -> list[EffectInstance]:
        if not reference_dominates(problem, self.name):
            return []
        return [EffectInstance(self.name, self, ("scale_error",), (0.0,))]

    def plausible(self, inst: EffectInstance, params: Any) -> bool:
        return bool(1.0 + float(params[0]) > 0.0)

    def implausible_reason(self, inst: EffectInstance, params: Any, problem: Any) -> str | None:
        gain = 1.0 + float(params[0])
        if not np.isfinite(gain):
            return None
        r = _fit_correlation(problem)
        if r is not None and r > 0:
            # the readings do not run against the reference: another error drives it
            return (
                f"scale fitted as {float(params[0]):+.4g} (a gain of {gain:.3g}) and rejected: a "
                "gain through zero is no sensor's. The readings do not run against the "
                f"reference (correlation {r:+.2f} on the fit part), so an error the model lacks "
                "so far (a bias, a time offset) pulled it there; it is tried again beside the "
                "others"
            )
        return (
            f"scale fitted as {float(params[0]):+.4g} (a gain of {gain:.3g}) and rejected: the "
            f"readings run against the reference {getattr(problem, 'quantity', 'value')}. A sign "
            "convention differs between them (the bundle's angles and rates are counter-"
            "clockwise positive, docs/bundle-format.md), or the sensor is mounted the other way "
            "up; no effect can stand in for that"
        )

    def estimate_bias(
        self, inst: EffectInstance, params: Any, problem: Any
    ) -> tuple[float, str] | None:
        # Regression dilution pulls a fitted gain towards 0 by up to the reference's noise
        # share (the heading's in heading space): by up to share * (1 + s) (a clean gyro
        # against a 12.5 Hz heading with 0.02 rad of noise: -14 % at 6 SE; a real -12 % read as
        # -17 % at 0.75 % SE). Below a share of 1 % it is not counted.
        in_heading = getattr(problem, "integrate_window_s", None) is not None
        if in_heading and getattr(problem, "heading_share", None) is None:
            return None  # a compass heading's stream: no share measured in heading space
        share = gain_share(problem)
        if not np.isfinite(share) or share <= NOTE_REFERENCE_NOISE_SHARE:
            return None
        return share * abs(1.0 + float(params[0])), (
            f"the reference's own noise ({100 * share:.2g} % of its variance) may pull a fitted "
            "gain towards 0 (regression dilution); measure it against a reference with less "
            "noise, or with more motion"
        )

    def not_a_sensor_error(
        self, inst: EffectInstance, params: Any, problem: Any
    ) -> str | None:
        gain = 1.0 + float(params[0])
        likely = gross_gain(gain)
        if likely is None:
            return None
        return (
            f"a gain of {gain:.4g}{likely}. A gain beyond {GROSS_GAIN:g}:1 is a unit, a time "
            "base or a conversion, not a sensor's error: fix it in the bundle "
            "(docs/bundle-format.md: SI units, t in seconds)"
        )

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        state.gain = state.gain * (1.0 + params[0])

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        return scalar_config(inst, params, problem, combine="mul")


def _fit_correlation(problem: Any) -> float | None:
    """Correlation of a scalar stream's readings with its reference on the fit part (None
    without one)."""
    y, u, t, split = (getattr(problem, k, None) for k in ("y", "u", "t", "split"))
    if y is None or u is None or t is None or split is None:
        return None
    m = split.mask(t, "fit")
    yf, uf = np.asarray(y, dtype=float)[m], np.asarray(u, dtype=float)[m]
    ok = np.isfinite(yf) & np.isfinite(uf)
    if ok.sum() < 3 or np.std(yf[ok]) == 0 or np.std(uf[ok]) == 0:
        return None
    return float(np.corrcoef(yf[ok], uf[ok])[0, 1])
