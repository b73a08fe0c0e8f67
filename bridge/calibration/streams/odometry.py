"""Odometry stream: dead reckoning against a reference trajectory, re-anchored in windows.

Wheel odometry (UMBmark's kinematics, Borenstein & Feng 1996, eq. 2-5), per step k::

    s_l = dL / tpm * 2 rho / (1 + rho)     s_r = dR / tpm * 2 / (1 + rho)
    ds  = (s_l + s_r) / 2                  dtheta = (s_r - s_l) / b
    theta_k = theta_{k-1} + dtheta         p_k = p_{k-1} + ds [cos, sin](theta_{k-1} + dtheta / 2)

with ``tpm`` ticks per metre, ``b`` the wheel base and ``rho`` the left/right wheel diameter ratio.
Odometry given as body speeds (``v, omega``) or as a dead-reckoned pose (``x, y, theta``) is turned
into ``ds, dtheta`` directly; then ``tick_scale`` scales ``ds`` and ``wheel_base`` scales
``dtheta`` (the parameters are reported as factors). In every form ``heading_drift`` takes
``d dt`` off each ``dtheta`` (a dead-reckoned heading that turns at ``d`` rad/s relative to the
truth).

Residual: the reference is cut into windows of ``window_s`` seconds; each window starts at the
reference pose of its first sample (re-anchored) and the dead-reckoned path is compared with the
reference positions in it. Without a reference heading, the window's start heading is the one
that best aligns the window (closed-form 2-D Procrustes rotation), so only the shape of the path
counts. The metric is the RMS position error over the score part's windows (m).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from koala_bridge.calibration.effects.base import EffectInstance
from koala_bridge.calibration.problem import FloatArray, Part, StreamProblem, apply_all
from numpy.typing import NDArray


@dataclass
class OdometryState:
    """What the effects change: ticks per metre, wheel base, diameter ratio, time offset,
    heading drift."""

    tpm: float
    wheel_base: float
    ratio: float = 1.0
    tau: float = 0.0
    distance_scale: float = 1.0
    yaw_scale: float = 1.0
    heading_drift: float = 0.0  # rad/s the dead-reckoned heading turns relative to the truth


@dataclass
class _Windows:
    ref_idx: NDArray[np.intp]  # reference samples scored
    anchor: NDArray[np.intp]  # index (into the reference) of each sample's window anchor
    label: NDArray[np.intp]  # window label per sample (0..n_windows-1)
    n: int


@dataclass
class OdometryProblem(StreamProblem):
    t_odo: FloatArray = field(default_factory=lambda: np.empty(0))
    d_left: FloatArray | None = None  # tick increments (N-1,)
    d_right: FloatArray | None = None
    ds: FloatArray | None = None  # or distance / heading increments (N-1,)
    dtheta: FloatArray | None = None
    t_ref: FloatArray = field(default_factory=lambda: np.empty(0))
    p_ref: FloatArray = field(default_factory=lambda: np.empty((0, 2)))
    theta_ref: FloatArray | None = None
    tpm: float = 1.0
    wheel_base: float = 1.0
    ratio: float = 1.0  # declared left/right wheel diameter ratio
    window_s: float = 10.0
    form: str = "ticks"
    start_pose: tuple[float, float, float] | None = None  # (t, theta) known at the start

    def __post_init__(self) -> None:
        inside = (self.t_ref >= self.t_odo[0]) & (self.t_ref <= self.t_odo[-1])
        self._windows = {
            p: self._make_windows(inside & self.split.mask(self.t_ref, p), p)
            for p in ("fit", "score")
        }
        self._windows["all"] = self._make_windows(inside, "all")

    def _make_windows(self, m: NDArray[np.bool_], part: str) -> _Windows:
        idx = np.flatnonzero(m)
        if idx.size == 0:
            e = np.empty(0, dtype=np.intp)
            return _Windows(e, e, e, 0)
        t = self.t_ref[idx]
        label = np.floor((t - t[0]) / self.window_s).astype(np.intp)
        _, label = np.unique(label, return_inverse=True)
        first = np.r_[0, np.flatnonzero(np.diff(label)) + 1]
        anchor = idx[first][label]
        return _Windows(idx, anchor, label, int(label.max()) + 1)

    def state(self) -> OdometryState:
        return OdometryState(self.tpm, self.wheel_base, self.ratio)

    def dead_reckon(self, st: OdometryState) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Cumulative pose (x, y, theta) at the odometry times, from (0, 0, 0)."""
        if self.d_left is not None and self.d_right is not None:
            k_l = 2 * st.ratio / (1 + st.ratio) / st.tpm
            k_r = 2 / (1 + st.ratio) / st.tpm
            s_l, s_r = self.d_left * k_l, self.d_right * k_r
            ds = 0.5 * (s_l + s_r)
            dth = (s_r - s_l) / st.wheel_base
        else:
            assert self.ds is not None and self.dtheta is not None
            ds = self.ds * st.distance_scale
            dth = self.dtheta * st.yaw_scale
        if st.heading_drift:
            dth = dth - st.heading_drift * np.diff(self.t_odo)
        th = np.r_[0.0, np.cumsum(dth)]
        mid = th[:-1] + 0.5 * dth
        x = np.r_[0.0, np.cumsum(ds * np.cos(mid))]
        y = np.r_[0.0, np.cumsum(ds * np.sin(mid))]
        return x, y, th

    def _errors(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: str
    ) -> tuple[FloatArray, _Windows]:
        st = self.state()
        apply_all(st, self, insts, x)
        w = self._windows[part]
        if w.ref_idx.size == 0:
            return np.empty((0, 2)), w
        X, Y, TH = self.dead_reckon(st)
        tq = self.t_ref + st.tau
        xi = np.interp(tq, self.t_odo, X)
        yi = np.interp(tq, self.t_odo, Y)
        thi = np.interp(tq, self.t_odo, TH)
        j, a = w.ref_idx, w.anchor
        c, s = np.cos(thi[a]), np.sin(thi[a])
        dx, dy = xi[j] - xi[a], yi[j] - yi[a]
        d = np.column_stack([c * dx + s * dy, -s * dx + c * dy])  # in the anchor's body frame
        q = self.p_ref[j] - self.p_ref[a]
        if self.theta_ref is not None:
            phi = self.theta_ref[a]
        elif self.start_pose is not None:
            # Heading is not re-anchored: dead-reckoned from the declared start heading.
            t_s, th_s, _ = self.start_pose
            phi = th_s + thi[a] - float(np.interp(t_s + st.tau, self.t_odo, TH))
        else:
            cross = np.bincount(w.label, d[:, 0] * q[:, 1] - d[:, 1] * q[:, 0], w.n)
            dot = np.bincount(w.label, d[:, 0] * q[:, 0] + d[:, 1] * q[:, 1], w.n)
            phi = np.arctan2(cross, dot)[w.label]
        cp, sp = np.cos(phi), np.sin(phi)
        pred = np.column_stack([cp * d[:, 0] - sp * d[:, 1], sp * d[:, 0] + cp * d[:, 1]])
        return q - pred, w

    def residuals(
        self, insts: Sequence[EffectInstance], x: FloatArray, part: Part, for_fit: bool = False
    ) -> FloatArray:
        e, _ = self._errors(insts, x, part)
        return e.T.ravel()

    def metric_value(self, insts: Sequence[EffectInstance], x: FloatArray, part: Part) -> float:
        e, _ = self._errors(insts, x, part)
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if e.size else float("nan")

    def independent_count(self, part: Part) -> int | None:
        # Dead-reckoning errors integrate the noise twice (slip -> heading -> position), so
        # residuals inside a window are not independent whatever their lag-1 correlation says;
        # windows are (each starts from the reference), two coordinates each.
        return 2 * self._windows[part].n

    def residual_series(
        self, insts: Sequence[EffectInstance], x: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        e, w = self._errors(insts, x, "all")
        return self.t_ref[w.ref_idx], np.linalg.norm(e, axis=1)

    def describe(self) -> dict[str, Any]:
        return {
            "odometry_samples": int(self.t_odo.size),
            "reference_samples": int(self.t_ref.size),
            "form": self.form,
            "window_s": self.window_s,
            "reference_heading": self.theta_ref is not None,
            "windows": {"fit": self._windows["fit"].n, "score": self._windows["score"].n},
        }
