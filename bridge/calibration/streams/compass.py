"""Compass (magnetometer) stream: field vectors against a heading reference or against physics.

Correction model (the inverse of ``m = S m_true + h``, ArduPilot/PX4 style)::

    m_c = C (m - h),   C = (I + E) C_declared,   h = h_declared + delta_h

Three modes, chosen from the data:

* ``heading``: a reference heading exists (``truth_pose.theta``); planar. Residual is the heading
  error ``wrap(alpha - atan2(m_c,y, m_c,x) - theta_ref)`` in rad; ``alpha`` (direction of
  magnetic north in the world frame: declination plus mounting yaw) is a nuisance parameter.
  Where the declared world has local magnetic sources and the reference has positions, the
  field's declared direction at each position is subtracted from ``theta_ref`` first
  (``alpha`` is then the mounting yaw).

A declared motor-current disturbance ``M k (v_l, v_r)`` (wheel speeds from the odometry ticks)
is subtracted from ``m`` before the correction.
* ``magnitude_2d``: no reference, rotation about z only (the vertical component varies little):
  the horizontal field magnitude must be constant; residual ``|m_c,xy| / B - 1``.
* ``magnitude_3d``: no reference, rotation through many orientations: ``|m_c| / B - 1``.

``B`` (the field magnitude) is a nuisance parameter. The metric is the RMS heading error (rad) or,
with no reference, the spread std/mean of the (horizontal) field magnitude in percent.

In ``magnitude_2d`` mode a bundle with a gyro gives a second, heading metric: the compass
heading against the heading integrated from the gyro under its *declared* model
(``(yaw_rate - bias) / (1 + scale)``), the constant between the two (north) fitted on the fit
part as a circular mean, RMS of the wrapped difference on the score part. It is only as good as
the declared gyro: a gyro bias that nobody declared drifts that reference by ``bias * t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.problem import (
    FloatArray,
    LastResult,
    Part,
    SecondaryMetric,
    StreamProblem,
    apply_all,
)
from koala_bridge.core.geometry import wrap_angle
from numpy.typing import NDArray


@dataclass
class CompassState:
    """Hard-iron offset ``h`` (3,) and correction matrix ``C`` (3, 3) the effects change."""

    h: FloatArray
    C: FloatArray
    dims: int
    #: the readings' lag behind the reference heading (s; ``time_offset``)
    tau: float = 0.0


@dataclass
class CompassProblem(StreamProblem):
    t: FloatArray = field(default_factory=lambda: np.empty(0))
    m: FloatArray = field(default_factory=lambda: np.empty((0, 3)))
    mode: str = "magnitude_2d"
    theta_ref: FloatArray | None = None
    h_declared: FloatArray = field(default_factory=lambda: np.zeros(3))
    C_declared: FloatArray = field(default_factory=lambda: np.eye(3))
    uT_per_unit: float = 1.0
    data_unit: str = "uT"
    #: declared additive disturbance per sample (N, 3), data unit: the motor currents' field
    disturbance: FloatArray | None = None
    #: declared world-frame direction of the horizontal field at each sample's position (N,)
    #: (local sources), heading mode only; alpha is then a mounting yaw about it
    field_direction: FloatArray | None = None
    #: heading (rad, unwrapped) integrated from the bundle's gyro under its declared model, at
    #: each compass sample; ``magnitude_2d`` mode's second metric is held against it
    gyro_heading: FloatArray | None = None
    #: the reference heading (rad, unwrapped) at its own stamps ``ref_t``, heading mode: what
    #: ``time_offset`` reads at the readings' times shifted by ``tau``
    ref_t: FloatArray | None = None
    ref_heading: FloatArray | None = None
    #: the readings' median interval (s), where the stream's samples are not the readings
    #: (a sparse reference's samples, each with its share of readings)
    reading_dt: float | None = None

    def __post_init__(self) -> None:
        self._last = LastResult()
        fit = self.split.mask(self.t, "fit")
        self._masks = {"fit": fit, "score": ~fit, "all": np.ones_like(fit)}
        # the readings of each part with the declared motor field removed, and the nuisance
        # start values: computed once (every fit evaluates them; a 1-hour recording's masks
        # took most of its calibration time)
        self._m_parts: dict[str, FloatArray] = {}
        self._mT_parts: dict[str, FloatArray] = {}  # the same, (3, N) contiguous
        self._psi_parts: dict[tuple[str, float], FloatArray] = {}
        self._nuisance0: FloatArray | None = None

    def _m(self, part: str) -> FloatArray:
        m = self._m_parts.get(part)
        if m is None:
            mask = self._masks[part]
            m = self.m[mask]
            if self.disturbance is not None:
                m = m - self.disturbance[mask]
            self._m_parts[part] = m
        return m

    def _mT(self, part: str) -> FloatArray:
        """:meth:`_m` as (3, N), contiguous: ``C @ m.T`` is three times faster than ``m @ C.T``
        (numpy's matmul with a short inner axis), and every fit evaluates it."""
        mT = self._mT_parts.get(part)
        if mT is None:
            mT = self._mT_parts[part] = np.ascontiguousarray(self._m(part).T)
        return mT

    @property
    def dims(self) -> int:
        return 3 if self.mode == "magnitude_3d" else 2

    def state(self) -> CompassState:
        return CompassState(self.h_declared.copy(), self.C_declared.copy(), self.dims)

    def corrected(self, insts: Sequence[EffectInstance], x: FloatArray, part: str) -> FloatArray:
        return self._corrected(self._applied(insts, x), part)

    def _applied(self, insts: Sequence[EffectInstance], x: FloatArray) -> CompassState:
        st = self.state()
        apply_all(st, self, insts, x)
        return st

    def _corrected(self, st: CompassState, part: str) -> FloatArray:
        return (st.C @ (self._mT(part) - st.h[:, None])).T

    def _theta_field(self, mask: np.ndarray, tau: float = 0.0) -> FloatArray:
        """Reference heading minus the declared field direction (0 without one), at the
        readings' times less ``tau``."""
        assert self.theta_ref is not None
        if tau == 0.0:
            theta = self.theta_ref[mask]
        else:
            assert self.ref_t is not None and self.ref_heading is not None
            theta = np.interp(self.t[mask] - tau, self.ref_t, self.ref_heading)
        if self.field_direction is None:
            return theta
        return theta - self.field_direction[mask]

    def _psi(self, part: str, tau: float = 0.0) -> FloatArray:
        """:meth:`_theta_field` of a part, wrapped once: an hour's unwrapped reference heading
        runs to hundreds of radians, and every residual's wrap then cost five times as much.
        Kept for ``tau = 0`` and for the last other ``tau`` asked."""
        key = (part, tau)
        psi = self._psi_parts.get(key)
        if psi is None:
            psi = wrap_angle(self._theta_field(self._masks[part], tau))
            if tau != 0.0:  # the parts at this tau and at 0 are kept, other taus dropped
                for k in [k for k in self._psi_parts if k[1] not in (0.0, tau)]:
                    del self._psi_parts[k]
            self._psi_parts[key] = psi
        return psi

    def _declared_heading(self, part: str) -> FloatArray:
        """The heading of the readings under the declared model (no nuisance)."""
        m = self._m(part) - self.h_declared
        return self.heading(m @ self.C_declared.T)

    def heading_match(self, taus: FloatArray, rows: NDArray[np.intp] | None = None) -> FloatArray:
        """For each shift ``tau``: how well the declared model's heading on the fit part (its
        ``rows`` only, or all) follows the reference heading ``tau`` earlier, as
        ``r = sqrt(1 - v / max v)``: ``v`` the variance of their difference (about its circular
        mean) that a constant (north) and a first and second harmonic of the shifted heading
        leave (what a hard and a soft iron the declared model lacks make of it: with the mean
        resultant length alone, an undeclared hard iron lowered the match at every shift, the
        clocks' offset no longer stood out, and a compass 0.7 s off went unfound). ``1 - r^2``
        is ``v`` up to one factor, as a correlation's unexplained share (the clock search's
        test is a ratio of them). All 1 where no shift changes ``v`` beyond its noise (a robot
        that does not turn, or turns steadily: a shift is then a change of north)."""
        assert self.ref_t is not None and self.ref_heading is not None
        fit = self._masks["fit"]
        h, t = self._declared_heading("fit"), self.t[fit]
        field = None if self.field_direction is None else self.field_direction[fit]
        if rows is not None:
            h, t = h[rows], t[rows]
            field = None if field is None else field[rows]
        # every shift at once: (shifts, readings)
        taus = np.asarray(taus, dtype=float)
        theta = np.interp((t[None, :] - taus[:, None]).ravel(), self.ref_t, self.ref_heading)
        theta = theta.reshape(taus.size, t.size)
        if field is not None:
            theta -= field[None, :]
        d = h[None, :] - theta
        d = wrap_angle(d - np.arctan2(np.mean(np.sin(d), axis=1),
                                      np.mean(np.cos(d), axis=1))[:, None])
        c, s = np.cos(theta), np.sin(theta)
        # 1, cos a, sin a, cos 2a = 2 cos^2 a - 1, sin 2a = 2 sin a cos a
        X = np.stack([np.ones_like(c), c, s, 2 * c * c - 1, 2 * s * c], axis=1)
        v = _batch_residual(X, d)
        top = float(np.max(v))
        if not top > 0 or np.ptp(v) <= 3 * np.sqrt(2 / max(h.size, 1)) * float(np.min(v)):
            return np.ones(len(taus))
        return np.asarray(np.sqrt(np.clip(1 - v / top, 0.0, 1.0)), dtype=float)

    def latency_window(self) -> tuple[float, float]:
        """``(step, span)`` of the grid a latency is searched on
        (:func:`koala_bridge.calibration.effects.time_offset.latency_window`), the step half
        the readings' own interval: against a sparse reference the stream's samples are the
        reference's (a 1 s reference made the step 0.5 s, and every fitted offset lay "beyond"
        a window of 0.5 - 0.5 s)."""
        from koala_bridge.calibration.effects.time_offset import latency_window

        step, span = latency_window(self.t[self._masks["fit"]])
        if self.reading_dt is not None and span:
            step = 0.5 * self.reading_dt
        return (step, span) if span >= step > 0 else (0.0, 0.0)

    @cached_property
    def clocks_apart(self) -> tuple[float, float, float] | None:
        """``(tau, R, R_near)`` when the readings and the reference heading look stamped on
        clocks seconds apart (:func:`.time_offset.clock_grid`, :func:`.time_offset.clock_pick`
        with :meth:`heading_match` as the score), else None; heading mode only."""
        from koala_bridge.calibration.effects.time_offset import clock_grid, clock_pick

        if self.mode != "heading" or self.ref_t is None:
            return None
        grid = clock_grid(self.t[self._masks["fit"]], self.ref_t)
        if grid is None:
            return None
        taus, rows, span = grid
        return clock_pick(taus, self.heading_match(taus, rows), span)

    def nuisance_x0(self) -> FloatArray:
        if self._nuisance0 is None:
            fit = self._masks["fit"]
            m = (self._m("fit") - self.h_declared) @ self.C_declared.T
            if self.mode == "heading":
                a = self._theta_field(fit) + np.arctan2(m[:, 1], m[:, 0])
                self._nuisance0 = np.array(
                    [float(np.arctan2(np.mean(np.sin(a)), np.mean(np.cos(a))))])
            else:
                self._nuisance0 = np.array(
                    [float(np.mean(np.linalg.norm(m[:, : self.dims], axis=1)))])
        return self._nuisance0.copy()

    def orientation_spread(self, harmonic: int = 1) -> float:
        """How well the fit part's orientations determine an iron effect: the smallest standard
        deviation, over directions, of the orientation vector ``(cos k psi, sin k psi)`` (2-D;
        psi the reference heading, or without one the declared-corrected field's direction) or
        of the field's unit vector (3-D), ``k = harmonic``.

        A hard iron moves the heading (or the magnitude) by a first harmonic of the orientation,
        a soft iron by a second; with the constant (north, field magnitude) fitted, either is
        determined only along directions in which those harmonics vary. A robot that did not
        turn gives about 0 (its noise); a full turn 0.71. :data:`MIN_ORIENTATION_SPREAD` is the
        bar (a turn through about 100 degrees for k = 1, 50 for k = 2).
        """
        fit = self._masks["fit"]
        if self.mode == "heading":
            psi = self._theta_field(fit)
        else:
            m = self.m[fit] - (0.0 if self.disturbance is None else self.disturbance[fit])
            m = (m - self.h_declared) @ self.C_declared.T
            if self.dims == 3:
                u = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-300)
                return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(u.T))[0], 0.0)))
            psi = np.arctan2(m[:, 1], m[:, 0])
        if psi.size < 3:
            return 0.0
        v = np.column_stack([np.cos(harmonic * psi), np.sin(harmonic * psi)])
        return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(v.T))[0], 0.0)))

    def heading(self, mc: FloatArray) -> FloatArray:
        """Compass heading (rad, CCW, up to the constant alpha): -atan2(m_c,y, m_c,x)."""
        return np.asarray(-np.arctan2(mc[:, 1], mc[:, 0]), dtype=float)

    def _residual(self, insts: Sequence[EffectInstance], x: FloatArray, part: str) -> FloatArray:
        # a copy: least squares scales a robust loss's residual in place
        hit = self._last.get(insts, x, part)
        if hit is None:
            hit = self._last.put(insts, x, part, self._compute_residual(insts, x, part))
        return np.array(hit)

    def _compute_residual(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str
    ) -> FloatArray:
        st = self._applied(insts, x)
        mc = self._corrected(st, part)
        if self.mode == "heading":
            return wrap_angle(x[0] + self.heading(mc) - self._psi(part, st.tau))
        return np.linalg.norm(mc[:, : self.dims], axis=1) / x[0] - 1.0

    def residuals(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: Part, for_fit: bool = False
    ) -> FloatArray:
        return self._residual(insts, x, part)

    def metric_value(self, insts: Sequence[EffectInstance], x: FloatArray, part: Part) -> float:
        if self.mode == "heading":
            r = self._residual(insts, x, part)
            return float(np.sqrt(np.mean(r**2)))
        mag = np.linalg.norm(self.corrected(insts, x, part)[:, : self.dims], axis=1)
        return float(100.0 * np.std(mag) / np.mean(mag))

    def residual_series(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        return self.t, self._residual(insts, x, "all")

    def heldout_errors(self, insts: Sequence[EffectInstance], x: FloatArray) -> FloatArray:
        """Heading error (rad), or the field magnitude's deviation from the fitted one in % (the
        metric's unit; its RMS is then close to, not equal to, the held-out spread)."""
        r = self._residual(insts, x, "score")
        return r if self.mode == "heading" else 100.0 * r

    def heading_error_vs_gyro(self, insts: Sequence[EffectInstance], x: FloatArray) -> float:
        """Held-out RMS (rad) of the compass heading against the declared gyro's heading, north
        (the constant between them) fitted on the fit part."""
        assert self.gyro_heading is not None
        d = wrap_angle(self.heading(self.corrected(insts, x, "all")) - self.gyro_heading)
        fit, score = self._masks["fit"], self._masks["score"]
        north = float(np.arctan2(np.mean(np.sin(d[fit])), np.mean(np.cos(d[fit]))))
        return float(np.sqrt(np.mean(wrap_angle(d[score] - north) ** 2)))

    def secondary_metrics(
        self,
        before: tuple[Sequence[EffectInstance], FloatArray],
        after: tuple[Sequence[EffectInstance], FloatArray],
    ) -> list[SecondaryMetric]:
        if self.mode != "magnitude_2d" or self.gyro_heading is None:
            return []
        return [
            SecondaryMetric(
                "heading_error_vs_declared_gyro_rms",
                "rad",
                self.heading_error_vs_gyro(*before),
                self.heading_error_vs_gyro(*after),
            )
        ]

    def noise_estimate(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[str | None, float | None]:
        """Per-axis sigma (uT) of isotropic noise: the heading residual times the horizontal
        field, or the magnitude residual times the field."""
        r = self._residual(insts, x, "all")
        mc = self.corrected(insts, x, "all")
        field = float(
            np.mean(
                np.linalg.norm(mc[:, :2] if self.mode == "heading" else mc[:, : self.dims], axis=1)
            )
        )
        return "noise_sigma_uT", float(np.std(r)) * field * self.uT_per_unit

    def describe(self) -> dict[str, Any]:
        return {"samples": int(self.t.size), "mode": self.mode, "data_unit": self.data_unit}


def _solve(X: FloatArray, d: FloatArray) -> FloatArray:
    """Least squares of ``d`` on the rows of ``X`` by the normal equations (five harmonics of a
    heading that turns are well conditioned), by SVD where they are singular (no turn)."""
    try:
        return np.asarray(np.linalg.solve(X @ X.T, X @ d), dtype=float)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(X.T, d, rcond=None)[0], dtype=float)


def _batch_residual(X: FloatArray, d: FloatArray) -> FloatArray:
    """Per shift ``k``: the mean square of ``d[k]`` less its least squares on the rows of
    ``X[k]`` (normal equations, batched; :func:`_solve` for a singular one)."""
    A = np.einsum("kin,kjn->kij", X, X)
    b = np.einsum("kin,kn->ki", X, d)
    try:
        coef = np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        coef = np.stack([_solve(X[k], d[k]) for k in range(X.shape[0])])
    r = d - np.einsum("ki,kin->kn", coef, X)
    return np.asarray(np.mean(r * r, axis=1), dtype=float)
