"""``outlier:short`` / ``outlier:uniform``: a fraction ``p`` of readings are spurious, the rest
follow the model (a two-component mixture, :mod:`koala_bridge.calibration.robust`)::

    f(y) = (1 - p) N(y - y_hat; 0, sigma^2) + p g(y)
    short:    g = U(low, y_hat)     a first echo from nearer than the target
    uniform:  g = U(low, high)      a reading unrelated to the target

params (estimated by EM with the model, not by least squares): ``probability`` p,
``inlier_sigma`` sigma, the support ``low`` (and ``high``, both declared, held).

The physical reading (seeds/004 "Sensor Models"): a sonar's beam is a 22.9 deg cone (Webots
``Khepera3_USSensor`` aperture 0.4, two of its rays aimed up and down), and "when an object is
detected ... it can actually be anywhere within the beam arc": the reading is the *first* echo,
so the floor, a table edge or anything else inside the cone nearer than the target gives a reading
*shorter* than the true range, anywhere between the sonar's minimum range and the target. That is
``short``, with ``low`` the declared ``min_range_m`` (0 when none is declared), 0 when the data read
below it (the declared limit is then not this sensor's). Crosstalk and
the simulator's glitch (``sim/models/sonar.py``: ``U(min_range_m, max_range_m)``) are readings
at any range: ``uniform``, on the declared range limits, else on the fit part's reading span
widened by 10 % each side. Sonar streams get both, other metric range streams (UWB, lidar,
landmark ranges) ``uniform`` only: a UWB's spurious readings (non-line-of-sight) are long, not
short. A model holds one at most: the loop tries a second in place of the first
(:func:`calibration.selection.select_effects`).

Not proposed for other scalar streams (gyro, bearings, IR counts): the heavy tails of those in
the recordings tried came from the model, not from spurious readings (a gyro's reference rate
interpolated across step commands, IR counts clipped against a wall the simulator's robot
pushed into: ``test_calibration_wall_slip``), and naming them outliers would hide the model
error. Their fits still use the robust loss (``ScalarProblem.robust_scale``).

Proposed only when the declared model's fit-part residual is heavy-tailed beyond the outliers the
declared model already has (:meth:`ScalarProblem.robust_scale`); judged by the mixture's held-out
likelihood (:func:`koala_bridge.calibration.selection.judge`), so one parameter (``p``) is
tested: ``sigma`` replaces the Gaussian model's own. Writes
``[sensors.<stream>.calibration] outlier_<support> = {probability, inlier_sigma, low[, high]}``;
``uniform`` on a sonar with declared range limits is also the simulator's sonar glitch model, so
it writes ``glitch_probability`` too (like ``glitch``; the simulator config has no sonar key in
the written TOML yet, so both are in the comment block).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from koala_bridge.calibration.effects import register_effect
from koala_bridge.calibration.effects.base import Effect, EffectInstance
from koala_bridge.calibration.robust import mad_sigma, tail_count
from koala_bridge.core.distributions import norm_sf
from numpy.typing import NDArray


@register_effect("outlier")
class Outlier(Effect):
    kinds = frozenset({"scalar"})
    mixture = True

    def _propose(self, problem: Any) -> list[EffectInstance]:
        metric_range = problem.is_range and problem.curve_points is None and not problem.angle
        if not metric_range or problem.integrate_window_s is not None:
            return []
        if problem.robust_scale() is None:
            return []
        fit = problem.part("fit")
        r = problem.tail_residual()
        sigma = mad_sigma(r)
        # with a declared noise level per reading (a sonar's table) sigma is its multiple
        sigma_name = "inlier_sigma" if problem.noise_shape("fit") is None else "inlier_sigma_ratio"
        k, n = tail_count(r, 3.0)
        # start: the excess over the Gaussian share beyond 3 sigma, at least 1 %
        p0 = float(np.clip(k / max(n, 1) - 2 * norm_sf(3.0), 0.01, 0.3))
        out = []
        y_min, y_max = float(np.min(fit.y)), float(np.max(fit.y))
        if problem.range_limits is not None:
            # the declared limits, widened to the readings: a reading outside them proves the
            # sensor reads there (another sensor than the one declared, a limit stated loosely);
            # a support that excluded it would make it impossible and the fit would call it noise
            lo, hi = problem.range_limits
            if y_min < lo:
                lo = 0.0        # below the declared minimum: where it really ends is unknown
            if y_max > hi:
                hi = y_max + 0.1 * (y_max - y_min)
        else:
            pad = 0.1 * (y_max - y_min)
            lo, hi = max(y_min - pad, 0.0), y_max + pad
        if problem.section == "sensors.sonar":
            low = lo if problem.range_limits is not None else 0.0
            out.append(
                EffectInstance(
                    f"{self.name}:short",
                    self,
                    ("probability", sigma_name, "low"),
                    (p0, sigma, float(low)),
                    data={"support": "short"},
                )
            )
        out.append(
            EffectInstance(
                f"{self.name}:uniform",
                self,
                ("probability", sigma_name, "low", "high"),
                (p0, sigma, float(lo), float(hi)),
                data={"support": "uniform"},
            )
        )
        return out

    def absent(self, inst: EffectInstance) -> NDArray[np.float64]:
        """No spurious readings: ``p = 0``; sigma and the support are not the effect's size (main's
        ``Effect.absent`` hook, which ``--write-config`` holds the size against its SE with):
        their starting values, so the size is ``p`` and how far EM moved sigma."""
        return np.asarray([0.0, *inst.x0[1:]], dtype=float)

    def n_tested(self, inst: EffectInstance) -> int:
        return 1  # p; sigma replaces the Gaussian model's own, the support is not fitted

    def log_density(
        self,
        inst: EffectInstance,
        params: NDArray[np.float64],
        y: NDArray[np.float64],
        r: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """log g per reading (``-inf`` where a reading cannot be spurious); ``y`` the readings,
        ``r`` their residuals (``y_hat = y - r``)."""
        low = float(params[2])
        if inst.data["support"] == "short":
            y_hat = y - r
            width = y_hat - low
            ok = (y >= low) & (y <= y_hat) & (width > 0)
            with np.errstate(divide="ignore", invalid="ignore"):
                return np.where(ok, -np.log(np.where(ok, width, 1.0)), -np.inf)
        high = float(params[3])
        ok = (y >= low) & (y <= high)
        return np.where(ok, -np.log(max(high - low, 1e-300)), -np.inf)

    def apply(self, inst: EffectInstance, state: Any, params: Any) -> None:
        """The mixture does not change the prediction: it changes the likelihood."""

    def config(self, inst: EffectInstance, params: Any, problem: Any) -> dict[str, Any]:
        keys: dict[str, Any] = {
            f"calibration.outlier_{inst.data['support']}": {
                n: float(f"{v:.6g}") for n, v in zip(inst.param_names, params, strict=True)
            }
        }
        if (
            inst.data["support"] == "uniform"
            and problem.is_range
            and problem.range_limits is not None
            and problem.section == "sensors.sonar"
        ):
            keys["glitch_probability"] = float(f"{params[0]:.6g}")
        return keys
